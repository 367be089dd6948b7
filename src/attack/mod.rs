//! Image-space attacks used to evaluate how well a watermark survives distortions of rendered
//! views.
//!
//! - [`diff`]: differentiable versions on burn tensors for EOT training and embedding (noise,
//!   blur, rotation, scaling, crop, JPEG with a straight-through quantiser, brightness,
//!   contrast, chains, and random compositions from a configurable family).
//! - [`real`]: real (non-differentiable) distortions of 8-bit RGB images: JPEG round trip,
//!   rotation, scaling, crop, Gaussian blur, Gaussian noise, brightness, contrast and chains of
//!   them ([`RealAttack`]), plus the paper's robustness protocol ([`paper_protocol`]). Parameters
//!   are named and interpreted as in the baselines' public code (3D-GSW, GuardSplat, WateRF); in
//!   particular "Gaussian noise σ" adds noise of standard deviation σ² on [0, 1] images, and
//!   "crop 40 %" keeps 40 % of the area, centred.

pub mod diff;
pub mod model;
pub mod real;

pub use real::{
    AttackError, MAX_BLUR_KERNEL, MAX_OUTPUT_PIXELS, NormalRng, RealAttack, paper_protocol,
};
