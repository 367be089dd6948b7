mod error;
mod gaussians;
pub mod bounds;
pub mod camera;
pub use camera::Camera;
pub use error::SceneError;
pub use gaussians::{Gaussians, SH_C0, logit, normalize_quat, sh_coeffs, sigmoid};
