//! Replaying a view whose geometry is fixed: when only colours change (colour-only
//! finetuning, the default recipe), every pixel's compositing weights w_{i,p} = α_i·T_i stay
//! what they were, and the render is linear in the per-Gaussian colours:
//!
//! pixel_p = Σ_i c_i(view)·w_{i,p} + T_p·background,  ∂L/∂c_i = Σ_p w_{i,p}·∂L/∂pixel_p.
//!
//! A [`Replay`] records those weights once (one forward pass) and then renders and
//! back-propagates the view as a sparse product: no projection, sorting, binning or `exp`.
//! Its images are bit-identical to [`super::render`]'s for any colours of the same geometry
//! (the same products summed in the same order), and [`Replay::render`] refuses a scene whose
//! geometry (means, scales, rotations, opacities) is not the recorded one.

use rayon::prelude::*;

use super::forward::{TileRecord, render_recording, split_by_ranges};
use super::project::{Cam, colour_backward, sh_color};
use super::{Real, RenderError, RenderOptions, TILE};
use crate::scene::{Camera, Gaussians};

/// The compositing weights of one view of one geometry.
pub struct Replay<T> {
    width: usize,
    height: usize,
    cam: Cam<T>,
    sh_degree: u8,
    background: [T; 3],
    geometry: u64,
    n_gaussians: usize,
    /// Scene index of each visible Gaussian, in depth order.
    ids: Vec<u32>,
    tiles_x: usize,
    /// Per tile, its range in `runs`.
    tile_runs: Vec<(u32, u32)>,
    /// Per run: the visible Gaussian (index into `ids`) and the end of its contributions in
    /// `pix` / `w` (runs are consecutive within a tile; a tile's first run starts at its first
    /// contribution).
    runs: Vec<(u32, u32)>,
    /// Per tile, the start of its contributions.
    tile_starts: Vec<u32>,
    pix: Vec<u8>,
    w: Vec<T>,
    /// Per pixel (tile-major, 256 per tile): transmittance left after compositing.
    final_t: Vec<T>,
}

/// A hash of the parameters a render's weights depend on (all but the colours).
fn geometry_hash<T: Real>(g: &Gaussians<T>) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64 ^ g.len() as u64;
    let mut eat = |v: T| {
        h = (h ^ u64::from(v.as_f32().to_bits())).wrapping_mul(0x0000_0100_0000_01b3);
    };
    for i in 0..g.len() {
        g.means[i].iter().for_each(|&v| eat(v));
        g.log_scales[i].iter().for_each(|&v| eat(v));
        g.rotations[i].iter().for_each(|&v| eat(v));
        eat(g.opacity_logits[i]);
    }
    h
}

impl<T: Real> Replay<T> {
    /// Renders `g` through `camera` once and records its weights. Colour overrides
    /// ([`RenderOptions::colors`]) are not replayable.
    pub fn record(
        g: &Gaussians<T>,
        camera: &Camera,
        opts: &RenderOptions,
    ) -> Result<Self, RenderError> {
        if opts.colors.is_some() {
            return Err(RenderError::BadScene(
                "a replay recomputes SH colours; colour overrides cannot be replayed".into(),
            ));
        }
        let (r, records) = render_recording(g, camera, opts, true)?;
        let st = r.state;
        let mut tile_runs = Vec::with_capacity(records.len());
        let mut tile_starts = Vec::with_capacity(records.len());
        let total: usize = records.iter().map(|r| r.pix.len()).sum();
        let mut runs = Vec::new();
        let (mut pix, mut w) = (Vec::with_capacity(total), Vec::with_capacity(total));
        for (t, rec) in records.into_iter().enumerate() {
            let TileRecord {
                runs: tr,
                pix: tp,
                w: tw,
            } = rec;
            let (start, _) = st.tile_ranges[t];
            let base = pix.len() as u32;
            tile_runs.push((runs.len() as u32, (runs.len() + tr.len()) as u32));
            tile_starts.push(base);
            runs.extend(
                tr.into_iter()
                    .map(|(j, end)| (st.entries[(start + j) as usize], base + end)),
            );
            pix.extend(tp);
            w.extend(tw);
        }
        Ok(Self {
            width: st.cam.width,
            height: st.cam.height,
            sh_degree: st.sh_degree,
            background: st.background,
            geometry: geometry_hash(g),
            n_gaussians: g.len(),
            ids: st.splats.iter().map(|s| s.id).collect(),
            tiles_x: st.tiles_x,
            tile_runs,
            runs,
            tile_starts,
            pix,
            w,
            final_t: st.final_t,
            cam: st.cam,
        })
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        let t = std::mem::size_of::<T>();
        self.ids.len() * 4
            + self.tile_runs.len() * 12
            + self.runs.len() * 8
            + self.pix.len() * (1 + t)
            + self.final_t.len() * t
    }

    /// Contributions (pixel, Gaussian) recorded.
    pub fn contributions(&self) -> usize {
        self.pix.len()
    }

    fn check(&self, g: &Gaussians<T>) -> Result<(), RenderError> {
        if g.len() != self.n_gaussians || geometry_hash(g) != self.geometry {
            return Err(RenderError::BadScene(
                "the scene's geometry is not the one this replay recorded".into(),
            ));
        }
        Ok(())
    }

    fn colours(&self, g: &Gaussians<T>) -> Vec<([T; 3], [bool; 3])> {
        self.ids
            .par_iter()
            .with_min_len(1024)
            .map(|&i| sh_color(g, i as usize, &self.cam, self.sh_degree))
            .collect()
    }

    /// The view of `g` (same geometry as recorded, any colours): linear RGB, row-major, not
    /// clamped — bit-identical to [`super::render`]'s image.
    pub fn render(&self, g: &Gaussians<T>) -> Result<Vec<[T; 3]>, RenderError> {
        self.check(g)?;
        let colours = self.colours(g);
        let px = TILE * TILE;
        let mut tiled = vec![[T::zero(); 3]; self.tile_runs.len() * px];
        tiled.par_chunks_mut(px).enumerate().for_each(|(t, out)| {
            let (r0, r1) = self.tile_runs[t];
            let mut k = self.tile_starts[t] as usize;
            for &(splat, end) in &self.runs[r0 as usize..r1 as usize] {
                let c = colours[splat as usize].0;
                for (p, &w) in self.pix[k..end as usize]
                    .iter()
                    .zip(&self.w[k..end as usize])
                {
                    let o = &mut out[*p as usize];
                    for ch in 0..3 {
                        o[ch] = o[ch] + c[ch] * w;
                    }
                }
                k = end as usize;
            }
        });
        let bg = self.background;
        let mut image = vec![[T::zero(); 3]; self.width * self.height];
        image
            .par_chunks_mut(self.width)
            .enumerate()
            .for_each(|(y, row)| {
                let (ty, ly) = (y / TILE, y % TILE);
                for (x, out) in row.iter_mut().enumerate() {
                    let k = (ty * self.tiles_x + x / TILE) * px + ly * TILE + x % TILE;
                    let t = self.final_t[k];
                    *out = std::array::from_fn(|ch| tiled[k][ch] + t * bg[ch]);
                }
            });
        Ok(image)
    }

    /// This view with the Gaussians marked in `dropped` (scene-indexed) removed, as the model
    /// attack "remove Gaussians" removes them: each pixel's remaining contributions are
    /// recomposited front to back with their recorded opacities α_i = w_i / T_i, so a Gaussian
    /// behind a removed one shows through by 1/(1 − α) more. The result renders and
    /// back-propagates as a replay of the same geometry (colours of the kept Gaussians only).
    /// Exact but for the Gaussians the original render never reached (it stopped where
    /// T ≤ 1e-4; behind an opaque removed Gaussian they would now show).
    pub fn without(&self, dropped: &[bool]) -> Result<Self, RenderError> {
        let copies: Vec<u8> = dropped.iter().map(|&d| u8::from(!d)).collect();
        self.with_copies(&copies)
    }

    /// This view with `copies[i]` copies of Gaussian i (scene-indexed): 0 removes it (as
    /// [`Self::without`]), 1 keeps it, c > 1 composites it c times in place, as the model
    /// attack "clone Gaussians" does (a copy has its original's depth, so it composites right
    /// after it): its recorded opacity α becomes 1 − (1 − α)^c, its colour stays shared. Exact
    /// but for what the original render never reached (see [`Self::without`]) and for the
    /// rasterizer's cap of α at 0.99 per copy.
    pub fn with_copies(&self, copies: &[u8]) -> Result<Self, RenderError> {
        if copies.len() != self.n_gaussians {
            return Err(RenderError::BadScene(format!(
                "copies of {} Gaussians for a replay of {}",
                copies.len(),
                self.n_gaussians
            )));
        }
        let px = TILE * TILE;
        let mut w = vec![T::zero(); self.w.len()];
        let mut final_t = self.final_t.clone();
        let w_ranges: Vec<(u32, u32)> = (0..self.tile_runs.len())
            .map(|t| {
                let end = self
                    .tile_starts
                    .get(t + 1)
                    .copied()
                    .unwrap_or(self.w.len() as u32);
                (self.tile_starts[t], end)
            })
            .collect();
        let w_tiles = split_by_ranges(&mut w, &w_ranges);
        w_tiles
            .into_par_iter()
            .zip(final_t.par_chunks_mut(px))
            .enumerate()
            .for_each(|(t, (w_out, t_out))| {
                let (r0, r1) = self.tile_runs[t];
                let start = self.tile_starts[t] as usize;
                let mut t_orig = vec![T::one(); px];
                let mut t_new = vec![T::one(); px];
                let mut touched = vec![false; px];
                let mut k = start;
                for &(splat, end) in &self.runs[r0 as usize..r1 as usize] {
                    let c = copies[self.ids[splat as usize] as usize];
                    for (p, &wi) in self.pix[k..end as usize]
                        .iter()
                        .zip(&self.w[k..end as usize])
                    {
                        let p = *p as usize;
                        touched[p] = true;
                        let to = t_orig[p];
                        let alpha = if to > T::zero() { wi / to } else { T::zero() };
                        t_orig[p] = to * (T::one() - alpha);
                        if c > 0 {
                            let alpha = if c == 1 {
                                alpha
                            } else {
                                T::one() - (T::one() - alpha).powi(i32::from(c))
                            };
                            w_out[k - start] = alpha * t_new[p];
                            t_new[p] = t_new[p] * (T::one() - alpha);
                        }
                        k += 1;
                    }
                    k = end as usize;
                }
                for p in 0..px {
                    if touched[p] {
                        t_out[p] = t_new[p];
                    }
                }
            });
        Ok(Self {
            width: self.width,
            height: self.height,
            cam: self.cam.clone(),
            sh_degree: self.sh_degree,
            background: self.background,
            geometry: self.geometry,
            n_gaussians: self.n_gaussians,
            ids: self.ids.clone(),
            tiles_x: self.tiles_x,
            tile_runs: self.tile_runs.clone(),
            runs: self.runs.clone(),
            tile_starts: self.tile_starts.clone(),
            pix: self.pix.clone(),
            w,
            final_t,
        })
    }

    /// The Gaussian with the largest compositing weight α·T at pixel (`x`, `y`) and that
    /// weight; `None` where no Gaussian contributes (or outside the image).
    pub fn strongest_at(&self, x: usize, y: usize) -> Option<(u32, T)> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let t = (y / TILE) * self.tiles_x + x / TILE;
        let local = ((y % TILE) * TILE + x % TILE) as u8;
        let (r0, r1) = self.tile_runs[t];
        let mut k = self.tile_starts[t] as usize;
        let mut best: Option<(u32, T)> = None;
        for &(splat, end) in &self.runs[r0 as usize..r1 as usize] {
            for (p, &w) in self.pix[k..end as usize]
                .iter()
                .zip(&self.w[k..end as usize])
            {
                if *p == local && best.is_none_or(|(_, b)| w > b) {
                    best = Some((self.ids[splat as usize], w));
                }
            }
            k = end as usize;
        }
        best
    }

    /// ∂L/∂(SH coefficients) of `g` from `d_image` (∂L/∂pixel, row-major RGB): a scene-shaped
    /// gradient whose `sh_dc` and `sh_rest` are filled and whose geometry entries are zero
    /// (the geometry is held fixed; its gradient is not computed).
    pub fn backward(
        &self,
        g: &Gaussians<T>,
        d_image: &[[T; 3]],
    ) -> Result<Gaussians<T>, RenderError> {
        Ok(self
            .backward_each(g, &[d_image])?
            .pop()
            .expect("one gradient"))
    }

    /// [`Replay::backward`] of several image gradients at once (one pass over the recorded
    /// weights, the colours evaluated once): one scene-shaped gradient per entry of
    /// `d_images`, each equal to its own [`Replay::backward`].
    pub fn backward_each(
        &self,
        g: &Gaussians<T>,
        d_images: &[&[[T; 3]]],
    ) -> Result<Vec<Gaussians<T>>, RenderError> {
        self.check(g)?;
        for d in d_images {
            if d.len() != self.width * self.height {
                return Err(RenderError::GradientSize {
                    got: d.len(),
                    expected: self.width * self.height,
                });
            }
        }
        let kk = d_images.len();
        // Per run and gradient: Σ_p w·∂L/∂pixel_p, then summed per Gaussian in run order
        // (deterministic).
        let mut per_run = vec![[T::zero(); 3]; self.runs.len() * kk];
        let ranges: Vec<(u32, u32)> = self
            .tile_runs
            .iter()
            .map(|&(r0, r1)| (r0 * kk as u32, r1 * kk as u32))
            .collect();
        let slices = split_by_ranges(&mut per_run, &ranges);
        slices.into_par_iter().enumerate().for_each(|(t, out)| {
            let (tx, ty) = (t % self.tiles_x, t / self.tiles_x);
            let (x0, y0) = (tx * TILE, ty * TILE);
            let (r0, _) = self.tile_runs[t];
            let mut k = self.tile_starts[t] as usize;
            for (slots, &(_, end)) in out.chunks_exact_mut(kk).zip(&self.runs[r0 as usize..]) {
                for (p, &w) in self.pix[k..end as usize]
                    .iter()
                    .zip(&self.w[k..end as usize])
                {
                    let (lx, ly) = (*p as usize % TILE, *p as usize / TILE);
                    let at = (y0 + ly) * self.width + x0 + lx;
                    for (acc, d) in slots.iter_mut().zip(d_images) {
                        let d = d[at];
                        for ch in 0..3 {
                            acc[ch] = acc[ch] + w * d[ch];
                        }
                    }
                }
                k = end as usize;
            }
        });
        let colours = self.colours(g);
        let rest_len = g.rest_len();
        let stride = rest_len.max(1);
        let grads = (0..kk)
            .map(|j| {
                let mut d_colour = vec![[T::zero(); 3]; self.ids.len()];
                for (r, &(splat, _)) in self.runs.iter().enumerate() {
                    let (acc, d) = (&mut d_colour[splat as usize], per_run[r * kk + j]);
                    for ch in 0..3 {
                        acc[ch] = acc[ch] + d[ch];
                    }
                }
                let mut rest = vec![T::zero(); self.ids.len() * stride];
                let dc: Vec<[T; 3]> = self
                    .ids
                    .par_iter()
                    .zip(&colours)
                    .zip(&d_colour)
                    .zip(rest.par_chunks_mut(stride))
                    .map(|(((&i, &(_, clamped)), &d), rest_out)| {
                        colour_backward(
                            g,
                            i as usize,
                            &self.cam,
                            self.sh_degree,
                            clamped,
                            d,
                            &mut rest_out[..rest_len],
                        )
                        .0
                    })
                    .collect();
                let mut out = g.cast(|_| T::zero());
                for (k, &i) in self.ids.iter().enumerate() {
                    let i = i as usize;
                    out.sh_dc[i] = dc[k];
                    out.sh_rest[i * rest_len..(i + 1) * rest_len]
                        .copy_from_slice(&rest[k * stride..k * stride + rest_len]);
                }
                out
            })
            .collect();
        Ok(grads)
    }
}
