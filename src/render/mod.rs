//! The differentiable 3D-GS rasterizer: a CPU reference (this module, parallel over tiles) that
//! renders a scene through a camera and back-propagates ∂L/∂image to every Gaussian parameter.
//!
//! The image model is the INRIA one (Kerbl et al. 2023):
//! - EWA splatting: Σ′ = J W Σ Wᵀ Jᵀ + 0.3·I (a 0.3 px² low-pass), Gaussians behind the near
//!   plane are culled; the Jacobian's x/z and y/z are clamped to 1.3× the field of view.
//! - Per pixel, Gaussians are composited front to back in order of camera-space depth with
//!   α = min(0.99, o·e^(−σ)), σ = ½ dᵀ Σ′⁻¹ d; α < 1/255 is skipped; compositing stops before a
//!   Gaussian would bring the transmittance T below 1e-4; the background fills the remaining T.
//! - Colour from SH of degree 0–3 along the direction camera → Gaussian, + 0.5, clamped at 0;
//!   or, with [`RenderOptions::colors`], a given per-Gaussian colour used as is.
//!
//! Unlike INRIA, a Gaussian's screen footprint is the exact ellipse where α ≥ 1/255 (not a 3σ
//! square), so the image does not depend on how the screen is cut into 16×16 tiles.

mod backward;
mod forward;
pub mod gpu;
mod project;
mod replay;
pub mod sh;

pub use backward::{Gradients, backward};
pub use forward::{RenderStats, Rendered, render};
pub use replay::Replay;

use crate::scene::Camera;
use std::sync::Arc;

/// Row-major rotation matrix of a quaternion (w, x, y, z), the renderer's own (unit
/// quaternions; normalise first).
pub fn rotation_matrix<T: Real>(q: [T; 4]) -> [[T; 3]; 3] {
    project::quat_to_mat(q)
}

/// Tile edge in pixels.
pub const TILE: usize = 16;
/// Smallest α that is composited.
pub const ALPHA_MIN: f64 = 1.0 / 255.0;
/// Largest α of one Gaussian.
pub const ALPHA_MAX: f64 = 0.99;
/// Compositing stops before T would fall below this.
pub const T_MIN: f64 = 1e-4;
/// Screen-space low-pass added to the projected covariance (px²).
pub const LOW_PASS: f64 = 0.3;

/// Floating-point type the rasterizer computes in: f32 in the product, f64 in gradient tests.
pub trait Real:
    num_traits::Float + Default + Send + Sync + std::fmt::Debug + std::iter::Sum + 'static
{
    /// A constant converted to this type.
    fn c(x: f64) -> Self;
    fn from_f32(x: f32) -> Self;
    fn as_f32(self) -> f32;
}

impl Real for f32 {
    #[inline(always)]
    fn c(x: f64) -> Self {
        x as f32
    }
    #[inline(always)]
    fn from_f32(x: f32) -> Self {
        x
    }
    #[inline(always)]
    fn as_f32(self) -> f32 {
        self
    }
}

impl Real for f64 {
    #[inline(always)]
    fn c(x: f64) -> Self {
        x
    }
    #[inline(always)]
    fn from_f32(x: f32) -> Self {
        x as f64
    }
    #[inline(always)]
    fn as_f32(self) -> f32 {
        self as f32
    }
}

/// How to render.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderOptions {
    /// Colour behind everything, linear RGB in [0, 1].
    pub background: [f32; 3],
    /// Gaussians whose centre is closer than this (camera-space z) are culled.
    pub near: f32,
    /// Use at most this SH degree (`None`: the scene's own).
    pub sh_degree: Option<u8>,
    /// Also return Σ_p α_i T_i per Gaussian from the forward pass.
    pub blend_weights: bool,
    /// Per-Gaussian colour override (one linear RGB triple per Gaussian of the scene): when set,
    /// Gaussian i is composited with `colors[i]` as is (no SH, no +0.5, no clamp at 0) instead of
    /// its SH colour, so pixel = Σ_i `colors[i]`·α_i·T_i + T_final·background. The backward pass
    /// then gives ∂L/∂colors in [`Gradients::colors`] and zero SH gradients (the colour no longer
    /// depends on SH or, through the view direction, on the means). This is 3D-GS's
    /// `override_color` / `colors_precomp`, used by contribution pruning.
    pub colors: Option<Arc<[[f32; 3]]>>,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            background: [0.0; 3],
            near: 0.01,
            sh_degree: None,
            blend_weights: false,
            colors: None,
        }
    }
}

/// Why a render or its backward pass could not run.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RenderError {
    #[error("camera '{name}' is unusable: {why}")]
    BadCamera { name: String, why: String },
    #[error("scene is inconsistent: {0}")]
    BadScene(String),
    #[error("image gradient has {got} pixels, the render has {expected}")]
    GradientSize { got: usize, expected: usize },
    #[error("near plane must be positive and finite, got {0}")]
    BadNear(f32),
    /// The GPU path failed (device lost, out of memory, a limit): see [`gpu::GpuError`].
    #[error("the GPU rasterizer failed: {0}")]
    Device(String),
}

/// Largest image edge the rasterizer accepts.
pub const MAX_IMAGE_EDGE: u32 = 16384;

pub(crate) fn check_inputs<T: Real>(
    g: &crate::scene::Gaussians<T>,
    cam: &Camera,
    opts: &RenderOptions,
) -> Result<(), RenderError> {
    check_camera(cam, opts)?;
    check_scene(g, opts)
}

/// The camera and render options' part of [`check_inputs`].
pub(crate) fn check_camera(cam: &Camera, opts: &RenderOptions) -> Result<(), RenderError> {
    let bad = |why: &str| RenderError::BadCamera {
        name: cam.name.clone(),
        why: why.to_string(),
    };
    if cam.width == 0 || cam.height == 0 {
        return Err(bad("zero width or height"));
    }
    if cam.width > MAX_IMAGE_EDGE || cam.height > MAX_IMAGE_EDGE {
        return Err(bad(&format!("larger than {MAX_IMAGE_EDGE} px")));
    }
    let intr = [cam.fx, cam.fy, cam.cx, cam.cy];
    if intr.iter().any(|v| !v.is_finite()) || cam.fx <= 0.0 || cam.fy <= 0.0 {
        return Err(bad("focal lengths must be positive and finite"));
    }
    if cam
        .rotation
        .iter()
        .flatten()
        .chain(&cam.translation)
        .any(|v| !v.is_finite())
    {
        return Err(bad("pose is not finite"));
    }
    if !(opts.near.is_finite() && opts.near > 0.0) {
        return Err(RenderError::BadNear(opts.near));
    }
    Ok(())
}

/// The scene's part of [`check_inputs`] (with the colour override, which is per Gaussian).
pub(crate) fn check_scene<T: Real>(
    g: &crate::scene::Gaussians<T>,
    opts: &RenderOptions,
) -> Result<(), RenderError> {
    let n = g.len();
    let ok = g.log_scales.len() == n
        && g.rotations.len() == n
        && g.opacity_logits.len() == n
        && g.sh_dc.len() == n
        && g.sh_degree <= 3
        && g.sh_rest.len() == n * g.rest_len();
    if !ok {
        return Err(RenderError::BadScene(
            "parameter arrays disagree in length or SH degree".into(),
        ));
    }
    if let Some(c) = &opts.colors
        && c.len() != n
    {
        return Err(RenderError::BadScene(format!(
            "colour override has {} entries for {n} Gaussians",
            c.len()
        )));
    }
    Ok(())
}

/// Converts a linear [0, 1] float image to 8-bit RGB (clamped, rounded).
pub fn to_rgb8<T: Real>(width: u32, height: u32, pixels: &[[T; 3]]) -> image::RgbImage {
    let mut buf = Vec::with_capacity(pixels.len() * 3);
    for p in pixels {
        for c in p {
            let v = c.as_f32().clamp(0.0, 1.0);
            buf.push((v * 255.0 + 0.5) as u8);
        }
    }
    image::RgbImage::from_raw(width, height, buf).expect("buffer size matches the image size")
}

#[cfg(test)]
mod tests;
