//! splatmark: watermarking 3D Gaussian Splatting assets.
//!
//! Module map (see `docs/ARCHITECTURE.md`): [`scene`] holds the Gaussian model, file formats and
//! cameras; [`render`] the differentiable rasterizer.

// `!(x > y)` is used on purpose throughout: unlike `x <= y` it is also true when x is NaN, which
// is how bad values get rejected.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod alloc;
pub mod app;
pub mod attack;
pub mod cli;
pub mod config;
pub mod decoder;
pub mod embed;
pub mod fit;
pub mod http;
pub mod image_file;
pub mod queue;
pub mod render;
pub mod scene;
pub mod store;
pub mod verify;
