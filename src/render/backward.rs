//! Backward pass: ∂L/∂image → ∂L/∂(means, log-scales, quaternions, opacity logits, SH).
//!
//! Each tile walks its Gaussians back to front, reconstructing each pixel's transmittance from
//! the forward pass's final T (as INRIA's rasterizer does). Per-(tile, Gaussian) screen-space
//! gradients land in their own slots and are summed in a fixed order, so results do not depend
//! on thread scheduling.

use super::forward::{Rendered, State, split_by_ranges};
use super::project::{ScreenGrad, project, project_backward};
use super::{ALPHA_MAX, ALPHA_MIN, Real, RenderError, TILE};
use crate::scene::Gaussians;
use rayon::prelude::*;

/// Gradients of a scalar loss with respect to every Gaussian parameter, laid out exactly like
/// the scene (`params.means[i]` is `∂L/∂means[i]`, and so on), plus per-Gaussian blend weights.
pub struct Gradients<T> {
    pub params: Gaussians<T>,
    /// ∂L/∂c_i for the colour c_i that Gaussian i was composited with: the override colour when
    /// [`super::RenderOptions::colors`] was set (then the SH gradients in `params` are zero),
    /// else the SH colour after the clamp at 0. Equals Σ_p (∂L/∂pixel_p)·α_i·T_i per channel;
    /// 0 for Gaussians not seen.
    pub colors: Vec<[T; 3]>,
    /// Σ_p α_i·T_i over the pixels of this view (0 for Gaussians not seen).
    pub blend_weights: Vec<T>,
    /// ∂L/∂(x, y) of each Gaussian's projected centre in pixels (0 for Gaussians not seen):
    /// the view-space positional gradient that 3D-GS densification thresholds.
    pub screen_xy: Vec<[T; 2]>,
}

/// Back-propagates `d_image` (∂L/∂pixel, row-major RGB like [`Rendered::image`]) through the
/// render `fwd` of scene `g`, which must be the scene that was rendered.
pub fn backward<T: Real>(
    g: &Gaussians<T>,
    fwd: &Rendered<T>,
    d_image: &[[T; 3]],
) -> Result<Gradients<T>, RenderError> {
    let st = &fwd.state;
    if d_image.len() != fwd.image.len() {
        return Err(RenderError::GradientSize {
            got: d_image.len(),
            expected: fwd.image.len(),
        });
    }
    if g.len() != st.n_gaussians {
        return Err(RenderError::BadScene(format!(
            "the render was of {} Gaussians, the scene has {}",
            st.n_gaussians,
            g.len()
        )));
    }

    // 1. Per (tile, Gaussian) screen-space gradients.
    let mut per_entry = vec![(ScreenGrad::<T>::default(), T::zero()); st.entries.len()];
    let slices = split_by_ranges(&mut per_entry, &st.tile_ranges);
    slices
        .into_par_iter()
        .enumerate()
        .for_each(|(t, out)| backward_tile(st, t, d_image, out));

    // 2. Sum per splat, in entry order (deterministic).
    let mut per_splat = vec![(ScreenGrad::<T>::default(), T::zero()); st.splats.len()];
    for (&e, (sg, w)) in st.entries.iter().zip(&per_entry) {
        let acc = &mut per_splat[e as usize];
        add_screen(&mut acc.0, sg);
        acc.1 = acc.1 + *w;
    }

    // 3. Through the projection, per Gaussian in parallel.
    let rest_len = g.rest_len();
    let stride = rest_len.max(1);
    let mut rest = vec![T::zero(); st.splats.len() * stride];
    let grads: Vec<_> = st
        .splats
        .par_iter()
        .zip(&per_splat)
        .zip(rest.par_chunks_mut(stride))
        .map(|((s, (sg, _)), rest_out)| {
            let i = s.id as usize;
            let p = project(g, i, &st.cam, st.sh_degree)
                .expect("a Gaussian visible in the forward pass projects again");
            // An override colour depends on no parameter: nothing flows into SH or the means.
            let mut sg = *sg;
            if st.color_override {
                sg.color = [T::zero(); 3];
            }
            project_backward(
                g,
                i,
                &st.cam,
                st.sh_degree,
                &p,
                &sg,
                &mut rest_out[..rest_len],
            )
        })
        .collect();

    let n = g.len();
    let z3 = [T::zero(); 3];
    let mut params = Gaussians {
        means: vec![z3; n],
        log_scales: vec![z3; n],
        rotations: vec![[T::zero(); 4]; n],
        opacity_logits: vec![T::zero(); n],
        sh_dc: vec![z3; n],
        sh_rest: vec![T::zero(); n * rest_len],
        sh_degree: g.sh_degree,
    };
    let mut blend_weights = vec![T::zero(); n];
    let mut colors = vec![z3; n];
    let mut screen_xy = vec![[T::zero(); 2]; n];
    for (k, (s, pg)) in st.splats.iter().zip(grads).enumerate() {
        let i = s.id as usize;
        params.means[i] = pg.mean;
        params.log_scales[i] = pg.log_scale;
        params.rotations[i] = pg.rotation;
        params.opacity_logits[i] = pg.opacity_logit;
        params.sh_dc[i] = pg.dc;
        params.sh_rest[i * rest_len..(i + 1) * rest_len]
            .copy_from_slice(&rest[k * stride..k * stride + rest_len]);
        blend_weights[i] = per_splat[k].1;
        colors[i] = per_splat[k].0.color;
        screen_xy[i] = per_splat[k].0.xy;
    }
    Ok(Gradients {
        params,
        colors,
        blend_weights,
        screen_xy,
    })
}

#[inline(always)]
fn add_screen<T: Real>(acc: &mut ScreenGrad<T>, g: &ScreenGrad<T>) {
    for k in 0..2 {
        acc.xy[k] = acc.xy[k] + g.xy[k];
    }
    for k in 0..3 {
        acc.conic[k] = acc.conic[k] + g.conic[k];
        acc.color[k] = acc.color[k] + g.color[k];
    }
    acc.opacity = acc.opacity + g.opacity;
}

fn backward_tile<T: Real>(
    st: &State<T>,
    t: usize,
    d_image: &[[T; 3]],
    out: &mut [(ScreenGrad<T>, T)],
) {
    const N: usize = TILE * TILE;
    let tile = st.tile_rect(t);
    let [tx0, ty0, tx1, ty1] = tile;
    let (start, end) = st.tile_ranges[t];
    let entries = &st.entries[start as usize..end as usize];
    let base = t * N;
    let final_t = &st.final_t[base..base + N];
    let n_contrib = &st.n_contrib[base..base + N];
    let zero = T::zero();
    let one = T::one();

    let mut trans = [zero; N];
    let mut acc = [[zero; 3]; N];
    let mut last_alpha = [zero; N];
    let mut last_color = [[zero; 3]; N];
    let mut dpix = [[zero; 3]; N];
    let mut bg_dot = [zero; N];
    let width = st.cam.width;
    for py in ty0..ty1 {
        for px in tx0..tx1 {
            let p = ((py - ty0) as usize) * TILE + (px - tx0) as usize;
            trans[p] = final_t[p];
            dpix[p] = d_image[py as usize * width + px as usize];
            bg_dot[p] = (0..3).map(|ch| st.background[ch] * dpix[p][ch]).sum();
        }
    }
    let max_n = n_contrib.iter().copied().max().unwrap_or(0) as usize;
    let alpha_min = T::c(ALPHA_MIN);
    let alpha_max = T::c(ALPHA_MAX);
    let half = T::c(0.5);

    for j in (0..max_n.min(entries.len())).rev() {
        let s = &st.splats[entries[j] as usize];
        let [ca, cb, cc] = s.conic;
        let mut sg = ScreenGrad::<T>::default();
        let mut wsum = zero;
        s.for_pixels(tile, |p, sigma, dx, dy| {
            if j as u32 >= n_contrib[p] {
                return;
            }
            let gauss = (-sigma).exp();
            let og = s.opacity * gauss;
            let alpha = og.min(alpha_max);
            if alpha < alpha_min {
                return;
            }
            let t_p = trans[p] / (one - alpha);
            trans[p] = t_p;
            let w = alpha * t_p;
            wsum = wsum + w;
            let mut d_alpha = zero;
            for ch in 0..3 {
                acc[p][ch] = last_alpha[p] * last_color[p][ch] + (one - last_alpha[p]) * acc[p][ch];
                last_color[p][ch] = s.color[ch];
                d_alpha = d_alpha + (s.color[ch] - acc[p][ch]) * dpix[p][ch];
                sg.color[ch] = sg.color[ch] + w * dpix[p][ch];
            }
            d_alpha = d_alpha * t_p - final_t[p] / (one - alpha) * bg_dot[p];
            last_alpha[p] = alpha;
            if og < alpha_max {
                // α = o·G, G = e^(−σ), σ = ½a·dx² + b·dx·dy + ½c·dy², d = pixel − mean.
                sg.opacity = sg.opacity + gauss * d_alpha;
                let d_g = s.opacity * d_alpha * gauss; // ∂L/∂(−σ)
                sg.xy[0] = sg.xy[0] + d_g * (ca * dx + cb * dy);
                sg.xy[1] = sg.xy[1] + d_g * (cb * dx + cc * dy);
                sg.conic[0] = sg.conic[0] - d_g * half * dx * dx;
                sg.conic[1] = sg.conic[1] - d_g * dx * dy;
                sg.conic[2] = sg.conic[2] - d_g * half * dy * dy;
            }
        });
        out[j] = (sg, wsum);
    }
}
