//! splatmark: watermarking 3D Gaussian Splatting assets.
//!
//! Module map (see `docs/ARCHITECTURE.md`): [`scene`] holds the Gaussian model, file formats and
//! cameras; [`render`] the differentiable rasterizer.

pub mod render;
pub mod scene;
