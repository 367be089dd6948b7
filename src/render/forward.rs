//! Forward pass: project, sort by depth, bin into 16×16 tiles, composite each tile in parallel.

use super::project::{Cam, Projection, project};
use super::{ALPHA_MAX, ALPHA_MIN, Real, RenderError, RenderOptions, T_MIN, TILE, check_inputs};
use crate::scene::{Camera, Gaussians};
use rayon::prelude::*;

/// What the compositor needs of one visible Gaussian (compact, in depth order).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Splat<T> {
    /// Index of the Gaussian in the scene.
    pub id: u32,
    pub depth: T,
    pub xy: [T; 2],
    pub conic: [T; 3],
    pub opacity: T,
    pub color: [T; 3],
    /// σ threshold of the footprint: α ≥ 1/255 only where σ ≤ `thr` (with a small margin).
    pub thr: T,
    /// Pixel rectangle [x0, x1) × [y0, y1) containing the footprint, clipped to the image.
    pub rect: [u32; 4],
}

impl<T: Real> Splat<T> {
    fn new(id: usize, p: &Projection<T>, cam: &Cam<T>) -> Option<Self> {
        let o = p.opacity;
        if !(o >= T::c(ALPHA_MIN)) {
            return None;
        }
        // o·e^(−σ) ≥ 1/255  ⇔  σ ≤ ln(255·o); a margin keeps rounding from losing edge pixels.
        let thr = (o / T::c(ALPHA_MIN)).ln() + T::c(0.01);
        let r = (T::c(2.0) * thr * p.lambda_max).sqrt();
        let half = T::c(0.5);
        let x0 = (p.xy[0] - r - half).ceil();
        let x1 = (p.xy[0] + r - half).floor();
        let y0 = (p.xy[1] - r - half).ceil();
        let y1 = (p.xy[1] + r - half).floor();
        let (w, h) = (T::c(cam.width as f64), T::c(cam.height as f64));
        if !(x1 >= T::zero() && y1 >= T::zero() && x0 < w && y0 < h) {
            return None; // off screen (or NaN)
        }
        let clip = |v: T, hi: T| v.max(T::zero()).min(hi).as_f32() as u32;
        let rect = [
            clip(x0, w),
            clip(y0, h),
            clip(x1 + T::one(), w),
            clip(y1 + T::one(), h),
        ];
        if rect[0] >= rect[2] || rect[1] >= rect[3] {
            return None;
        }
        Some(Self {
            id: id as u32,
            depth: p.tc[2],
            xy: p.xy,
            conic: p.conic,
            opacity: o,
            color: p.color,
            thr,
            rect,
        })
    }

    /// Columns `[a, b)` of row `py` (within `[x0, x1)`) where the footprint can reach α ≥ 1/255.
    #[inline(always)]
    fn row_span(&self, dy: T, x0: u32, x1: u32) -> (u32, u32) {
        let [a, b, c] = self.conic;
        // ½a·dx² + b·dy·dx + (½c·dy² − thr) ≤ 0
        let disc = b * b * dy * dy - a * (c * dy * dy - T::c(2.0) * self.thr);
        if !(disc >= T::zero()) {
            return (x0, x0);
        }
        let sq = disc.sqrt();
        let half = T::c(0.5);
        let lo = self.xy[0] + (-b * dy - sq) / a - half;
        let hi = self.xy[0] + (-b * dy + sq) / a - half;
        let lo = lo.ceil().max(T::c(x0 as f64)).min(T::c(x1 as f64));
        let hi = (hi.floor() + T::one())
            .max(T::c(x0 as f64))
            .min(T::c(x1 as f64));
        (lo.as_f32() as u32, hi.as_f32() as u32)
    }

    /// Calls `f(p, σ, dx, dy)` for every pixel of the tile `[x0, y0, x1, y1]` (p = index within
    /// the 16×16 tile) that lies in this splat's footprint, with σ = ½dᵀΣ′⁻¹d at the pixel centre
    /// and d = centre − mean. Forward and backward both go through here, so they see exactly the
    /// same σ for every pixel.
    #[inline(always)]
    pub fn for_pixels(&self, tile: [u32; 4], mut f: impl FnMut(usize, T, T, T)) {
        let x0 = self.rect[0].max(tile[0]);
        let x1 = self.rect[2].min(tile[2]);
        let y0 = self.rect[1].max(tile[1]);
        let y1 = self.rect[3].min(tile[3]);
        let [a, b, c] = self.conic;
        let half = T::c(0.5);
        let half_a = half * a;
        for py in y0..y1 {
            let dy = T::c(py as f64) + half - self.xy[1];
            let (lo, hi) = self.row_span(dy, x0, x1);
            let row_c = half * c * dy * dy;
            let b_dy = b * dy;
            let row = ((py - tile[1]) as usize) * TILE;
            for px in lo..hi {
                let dx = T::c(px as f64) + half - self.xy[0];
                let sigma = dx * (half_a * dx + b_dy) + row_c;
                f(
                    (row + (px - tile[0]) as usize) & (TILE * TILE - 1),
                    sigma,
                    dx,
                    dy,
                );
            }
        }
    }

    /// Tile columns `[a, b)` touched by the footprint within tile row `ty` (pixel rows
    /// `[y0, y1)`): the exact x-extent of the ellipse over that band of pixel centres.
    fn band_tiles(&self, y0: u32, y1: u32, tiles_x: usize) -> (u32, u32) {
        let [a, b, c] = self.conic;
        let half = T::c(0.5);
        let det = a * c - b * b;
        let dy_max = (T::c(2.0) * a * self.thr / det).sqrt();
        let lo_dy = (T::c(y0 as f64) + half - self.xy[1]).max(-dy_max);
        let hi_dy = (T::c(y1 as f64) - half - self.xy[1]).min(dy_max);
        if !(lo_dy <= hi_dy) {
            return (0, 0);
        }
        let disc = |dy: T| {
            (T::c(2.0) * a * self.thr - det * dy * dy)
                .max(T::zero())
                .sqrt()
        };
        let left = |dy: T| (-b * dy - disc(dy)) / a;
        let right = |dy: T| (-b * dy + disc(dy)) / a;
        // Extreme x of the whole ellipse and the dy where it is reached.
        let dx_max = (T::c(2.0) * self.thr * c / det).sqrt();
        let dy_at_right = -b * dx_max / c;
        let in_band = |dy: T| dy >= lo_dy && dy <= hi_dy;
        let r = if in_band(dy_at_right) {
            dx_max
        } else {
            right(lo_dy).max(right(hi_dy))
        };
        let l = if in_band(-dy_at_right) {
            -dx_max
        } else {
            left(lo_dy).min(left(hi_dy))
        };
        let px_lo = (self.xy[0] + l - half)
            .ceil()
            .max(T::c(self.rect[0] as f64));
        let px_hi = (self.xy[0] + r - half)
            .floor()
            .min(T::c(self.rect[2] as f64 - 1.0));
        if !(px_lo <= px_hi) {
            return (0, 0);
        }
        let t = TILE as u32;
        let a0 = px_lo.as_f32() as u32 / t;
        let a1 = (px_hi.as_f32() as u32 / t + 1).min(tiles_x as u32);
        (a0, a1)
    }
}

/// Counts that describe one render.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct RenderStats {
    /// Gaussians in front of the near plane, non-degenerate and on screen.
    pub visible: usize,
    /// (tile, Gaussian) pairs composited.
    pub tile_entries: usize,
}

/// The result of a forward pass; keep it to run [`super::backward`](fn@super::backward).
pub struct Rendered<T> {
    pub width: u32,
    pub height: u32,
    /// Linear RGB, row-major, not clamped.
    pub image: Vec<[T; 3]>,
    /// Σ_p α_i·T_i per Gaussian of the scene, when [`RenderOptions::blend_weights`] is set.
    pub blend_weights: Option<Vec<T>>,
    pub stats: RenderStats,
    pub(crate) state: State<T>,
}

impl<T: Real> Rendered<T> {
    /// Screen radius in pixels of every Gaussian drawn, as (index in the scene, radius): half
    /// the longer side of the pixel rectangle its α ≥ 1/255 footprint covers on screen (INRIA's
    /// `radii`, which 3D-GS densification uses to prune Gaussians grown too large on screen).
    pub fn screen_radii(&self) -> impl Iterator<Item = (usize, f32)> + '_ {
        self.state.splats.iter().map(|s| {
            let [x0, y0, x1, y1] = s.rect;
            (s.id as usize, 0.5 * (x1 - x0).max(y1 - y0) as f32)
        })
    }
}

/// What the backward pass needs from the forward pass.
pub(crate) struct State<T> {
    pub cam: Cam<T>,
    pub sh_degree: u8,
    /// The colours came from [`RenderOptions::colors`], not from SH.
    pub color_override: bool,
    pub n_gaussians: usize,
    pub background: [T; 3],
    /// Visible Gaussians in depth order.
    pub splats: Vec<Splat<T>>,
    pub tiles_x: usize,
    /// Per tile, its range in `entries`.
    pub tile_ranges: Vec<(u32, u32)>,
    /// Indices into `splats`, grouped by tile, in depth order within each tile.
    pub entries: Vec<u32>,
    /// Per pixel (tile-major, 256 per tile): transmittance left after compositing.
    pub final_t: Vec<T>,
    /// Per pixel (tile-major): index within its tile's entries after the last contributor.
    pub n_contrib: Vec<u32>,
}

impl<T> State<T> {
    /// Pixel rectangle of tile `t`: x0, y0, x1, y1.
    pub fn tile_rect(&self, t: usize) -> [u32; 4] {
        let (tx, ty) = (t % self.tiles_x, t / self.tiles_x);
        let x0 = (tx * TILE) as u32;
        let y0 = (ty * TILE) as u32;
        [
            x0,
            y0,
            (x0 + TILE as u32).min(self.cam.width as u32),
            (y0 + TILE as u32).min(self.cam.height as u32),
        ]
    }
}

/// Renders `g` through `camera`.
pub fn render<T: Real>(
    g: &Gaussians<T>,
    camera: &Camera,
    opts: &RenderOptions,
) -> Result<Rendered<T>, RenderError> {
    render_recording(g, camera, opts, false).map(|(r, _)| r)
}

/// The contributions one tile composited, in compositing order: for each of the tile's entries
/// that reached a pixel, its index `j` in the tile's entry list and the end of its run in `pix`
/// / `w` (the pixel within the tile and the weight α·T it was composited with).
#[derive(Default)]
pub(crate) struct TileRecord<T> {
    pub runs: Vec<(u32, u32)>,
    pub pix: Vec<u8>,
    pub w: Vec<T>,
}

impl<T> TileRecord<T> {
    #[inline(always)]
    fn push(&mut self, j: u32, p: u8, w: T) {
        let end = self.pix.len() as u32 + 1;
        match self.runs.last_mut() {
            Some(run) if run.0 == j => run.1 = end,
            _ => self.runs.push((j, end)),
        }
        self.pix.push(p);
        self.w.push(w);
    }
}

/// [`render`], also returning every tile's [`TileRecord`] when `record` is set (empty ones
/// otherwise).
pub(crate) fn render_recording<T: Real>(
    g: &Gaussians<T>,
    camera: &Camera,
    opts: &RenderOptions,
    record: bool,
) -> Result<(Rendered<T>, Vec<TileRecord<T>>), RenderError> {
    check_inputs(g, camera, opts)?;
    let cam = Cam::<T>::new(camera, opts.near);
    let overrides = opts.colors.as_deref();
    // With a colour override the SH colour is not used: evaluate only its cheap DC term.
    let sh_degree = match overrides {
        Some(_) => 0,
        None => opts.sh_degree.map_or(g.sh_degree, |d| d.min(g.sh_degree)),
    };

    let unsorted: Vec<Splat<T>> = (0..g.len())
        .into_par_iter()
        .with_min_len(1024)
        .filter_map(|i| {
            let mut p = project(g, i, &cam, sh_degree)?;
            if let Some(c) = overrides {
                p.color = c[i].map(T::from_f32);
                p.clamped = [false; 3];
            }
            Splat::new(i, &p, &cam)
        })
        .collect();
    // Sort (depth, position) keys rather than the splats themselves: depths are positive, so
    // their f32 bit patterns order like the values; ties keep scene order.
    let mut keys: Vec<u64> = unsorted
        .iter()
        .enumerate()
        .map(|(k, s)| ((s.depth.as_f32().to_bits() as u64) << 32) | k as u64)
        .collect();
    keys.par_sort_unstable();
    let splats: Vec<Splat<T>> = keys
        .par_iter()
        .map(|&k| unsorted[(k & 0xFFFF_FFFF) as usize])
        .collect();
    drop(unsorted);

    let tiles_x = cam.width.div_ceil(TILE);
    let tiles_y = cam.height.div_ceil(TILE);
    let (tile_ranges, entries) = bin(&splats, tiles_x, tiles_y);
    let n_tiles = tiles_x * tiles_y;
    let px = TILE * TILE;

    let mut color = vec![[T::zero(); 3]; n_tiles * px];
    let mut final_t = vec![T::one(); n_tiles * px];
    let mut n_contrib = vec![0u32; n_tiles * px];
    let mut weights = vec![T::zero(); entries.len()];
    let weight_slices = split_by_ranges(&mut weights, &tile_ranges);

    let mut state = State {
        cam,
        sh_degree,
        color_override: overrides.is_some(),
        n_gaussians: g.len(),
        background: opts.background.map(T::from_f32),
        splats,
        tiles_x,
        tile_ranges,
        entries,
        final_t: Vec::new(),
        n_contrib: Vec::new(),
    };
    let records: Vec<TileRecord<T>> = {
        let st = &state;
        color
            .par_chunks_mut(px)
            .zip(final_t.par_chunks_mut(px))
            .zip(n_contrib.par_chunks_mut(px))
            .zip(weight_slices)
            .enumerate()
            .map(|(t, (((c, tt), n), w))| {
                let mut rec = TileRecord::default();
                if record {
                    raster_tile(st, t, c, tt, n, w, |j, p, w| rec.push(j as u32, p as u8, w));
                } else {
                    raster_tile(st, t, c, tt, n, w, |_, _, _| {});
                }
                rec
            })
            .collect()
    };

    // Tile-major → row-major, adding the background behind what is left of T.
    let (w, h) = (state.cam.width, state.cam.height);
    let bg = state.background;
    let mut image = vec![[T::zero(); 3]; w * h];
    image.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let ty = y / TILE;
        let ly = y % TILE;
        for (x, out) in row.iter_mut().enumerate() {
            let k = (ty * tiles_x + x / TILE) * px + ly * TILE + x % TILE;
            let t = final_t[k];
            *out = std::array::from_fn(|ch| color[k][ch] + t * bg[ch]);
        }
    });

    let blend_weights = opts.blend_weights.then(|| reduce_weights(&state, &weights));
    let stats = RenderStats {
        visible: state.splats.len(),
        tile_entries: state.entries.len(),
    };
    state.final_t = final_t;
    state.n_contrib = n_contrib;
    Ok((
        Rendered {
            width: w as u32,
            height: h as u32,
            image,
            blend_weights,
            stats,
            state,
        },
        records,
    ))
}

/// Groups splats by the tiles their rectangles touch, keeping depth order within each tile.
fn bin<T: Real>(
    splats: &[Splat<T>],
    tiles_x: usize,
    tiles_y: usize,
) -> (Vec<(u32, u32)>, Vec<u32>) {
    let t = TILE as u32;
    // Visit every (tile, splat) pair whose tile the ellipse really touches.
    let for_tiles = |s: &Splat<T>, f: &mut dyn FnMut(usize)| {
        for ty in s.rect[1] / t..(s.rect[3] - 1) / t + 1 {
            let y0 = (ty * t).max(s.rect[1]);
            let y1 = ((ty + 1) * t).min(s.rect[3]);
            let (a, b) = s.band_tiles(y0, y1, tiles_x);
            let row = ty as usize * tiles_x;
            for tx in a..b {
                f(row + tx as usize);
            }
        }
    };
    let mut counts = vec![0u32; tiles_x * tiles_y];
    for s in splats {
        for_tiles(s, &mut |k| counts[k] += 1);
    }
    let mut ranges = Vec::with_capacity(counts.len());
    let mut acc = 0u32;
    for &c in &counts {
        ranges.push((acc, acc + c));
        acc += c;
    }
    let mut cursor: Vec<u32> = ranges.iter().map(|r| r.0).collect();
    let mut entries = vec![0u32; acc as usize];
    for (k, s) in splats.iter().enumerate() {
        for_tiles(s, &mut |tile| {
            let c = &mut cursor[tile];
            entries[*c as usize] = k as u32;
            *c += 1;
        });
    }
    (ranges, entries)
}

/// Splits `v` into the consecutive, non-overlapping `ranges` (which must cover it in order).
pub(crate) fn split_by_ranges<'a, U>(
    mut v: &'a mut [U],
    ranges: &[(u32, u32)],
) -> Vec<&'a mut [U]> {
    let mut out = Vec::with_capacity(ranges.len());
    for &(a, b) in ranges {
        let (head, tail) = v.split_at_mut((b - a) as usize);
        out.push(head);
        v = tail;
    }
    out
}

fn reduce_weights<T: Real>(st: &State<T>, per_entry: &[T]) -> Vec<T> {
    let mut out = vec![T::zero(); st.n_gaussians];
    for (&e, &w) in st.entries.iter().zip(per_entry) {
        let id = st.splats[e as usize].id as usize;
        out[id] = out[id] + w;
    }
    out
}

/// Composites tile `t`; `sink(j, p, w)` sees every contribution (entry j of the tile, pixel p
/// within it, weight α·T) in compositing order.
fn raster_tile<T: Real>(
    st: &State<T>,
    t: usize,
    color_out: &mut [[T; 3]],
    trans_out: &mut [T],
    n_contrib_out: &mut [u32],
    weights: &mut [T],
    mut sink: impl FnMut(usize, usize, T),
) {
    const N: usize = TILE * TILE;
    let tile = st.tile_rect(t);
    let [tx0, ty0, tx1, ty1] = tile;
    let (start, end) = st.tile_ranges[t];
    let entries = &st.entries[start as usize..end as usize];
    let mut done = [true; N];
    for ly in 0..(ty1 - ty0) as usize {
        for lx in 0..(tx1 - tx0) as usize {
            done[ly * TILE + lx] = false;
        }
    }
    let mut n_done = N - ((tx1 - tx0) * (ty1 - ty0)) as usize;
    let mut trans = [T::one(); N];
    let mut color = [[T::zero(); 3]; N];
    let mut n_contrib = [0u32; N];
    let alpha_min = T::c(ALPHA_MIN);
    let alpha_max = T::c(ALPHA_MAX);
    let t_min = T::c(T_MIN);
    for (j, &e) in entries.iter().enumerate() {
        if n_done == N {
            break;
        }
        let s = &st.splats[e as usize];
        let mut wsum = T::zero();
        s.for_pixels(tile, |p, sigma, _, _| {
            if done[p] {
                return;
            }
            let alpha = (s.opacity * (-sigma).exp()).min(alpha_max);
            if alpha < alpha_min {
                return;
            }
            let t_p = trans[p];
            let test_t = t_p * (T::one() - alpha);
            if test_t < t_min {
                done[p] = true;
                n_done += 1;
                return;
            }
            let w = alpha * t_p;
            sink(j, p, w);
            for (c, sc) in color[p].iter_mut().zip(s.color) {
                *c = *c + sc * w;
            }
            wsum = wsum + w;
            trans[p] = test_t;
            n_contrib[p] = j as u32 + 1;
        });
        weights[j] = wsum;
    }
    color_out.copy_from_slice(&color);
    trans_out.copy_from_slice(&trans);
    n_contrib_out.copy_from_slice(&n_contrib);
}
