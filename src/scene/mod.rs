//! Scenes: the Gaussian model, the file formats people have (INRIA PLY, SuperSplat compressed
//! PLY, antimatter15 `.splat`, Niantic `.spz`, PlayCanvas SOG) and cameras (INRIA `cameras.json`, NeRF
//! `transforms.json`, LLFF `poses_bounds.npy`, orbit views).

mod error;
mod gaussians;

pub mod bounds;
pub mod camera;
pub mod colmap;
pub mod compressed_ply;
pub mod cost;
pub mod format;
pub mod orbit;
pub mod ply;
pub mod sog;
pub mod splat;
pub mod spz;
pub mod synthetic;
pub mod zip;

pub use camera::Camera;
pub use error::SceneError;
pub use format::{Format, Limits, read_scene, read_scene_bytes, write_ply, write_scene};
pub use gaussians::{Gaussians, SH_C0, logit, normalize_quat, rest_len_for, sh_coeffs, sigmoid};
