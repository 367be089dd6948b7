//! Attribution pictures — where the message lives and why, seen through a camera: the render,
//! the scene with every Gaussian coloured by its role (carriers red, compensators blue,
//! untouched grey), a heatmap of each Gaussian's share of the watermark gradient, the
//! difference to the original magnified ×10 (as in the paper's figures), and which Gaussian a
//! pixel shows most. `splatmark explain` and the console's attribution viewer
//! (`GET /v1/assets/{id}/attribution/picture`, `…/pick`) both draw through [`Pictures`].

use std::sync::OnceLock;

use serde::{Deserialize, Serialize};

use super::attribution::AttributionRecord;
use super::sbag::Role;
use crate::render::{RenderError, RenderOptions, Replay, render, to_rgb8};
use crate::scene::{Camera, Gaussians, SH_C0};

/// Role colours (linear RGB): carriers, compensators, untouched.
pub const CARRIER: [f32; 3] = [0.95, 0.15, 0.1];
pub const COMPENSATOR: [f32; 3] = [0.1, 0.35, 0.95];
pub const UNTOUCHED: [f32; 3] = [0.55, 0.55, 0.55];

/// One picture of a view.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Layer {
    /// The watermarked scene as a viewer sees it.
    View,
    /// Every Gaussian in its role's colour.
    Roles,
    /// Every Gaussian coloured by its share of the watermark gradient (black → red → yellow →
    /// white, white at the 99th percentile of the non-zero shares).
    Heat,
    /// |watermarked − original| × 10, per channel (needs the original).
    Diff,
}

impl Layer {
    /// Every layer, in the order pages show them.
    pub const ALL: [Layer; 4] = [Layer::View, Layer::Roles, Layer::Heat, Layer::Diff];

    /// The name used in file names and query strings.
    pub fn as_str(self) -> &'static str {
        match self {
            Layer::View => "view",
            Layer::Roles => "roles",
            Layer::Heat => "heat",
            Layer::Diff => "diff",
        }
    }

    /// The layer named `s` (as [`Layer::as_str`] writes it).
    pub fn parse(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|l| l.as_str() == s)
    }
}

/// Why pictures cannot be drawn.
#[derive(Debug, thiserror::Error)]
pub enum ExplainError {
    #[error(
        "{records} attribution records for a scene of {gaussians} Gaussians: they are not this scene's"
    )]
    Mismatch { records: usize, gaussians: usize },
    #[error("the difference picture needs the original scene")]
    NoOriginal,
    #[error("pixel ({x}, {y}) is outside the {width}×{height} view")]
    OutOfView {
        x: u32,
        y: u32,
        width: u32,
        height: u32,
    },
    #[error(transparent)]
    Render(#[from] RenderError),
}

/// Counts of a scene's attribution, as the pictures' legends state them.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Legend {
    pub gaussians: usize,
    pub carriers: usize,
    pub compensators: usize,
    pub untouched: usize,
    /// The carriers' share of the watermark gradient (0–1).
    pub carrier_share: f64,
    /// The share drawn white in the heatmap.
    pub heat_white_at: f32,
}

/// What a pixel shows most: the Gaussian with the largest compositing weight α·T there.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Pick {
    pub index: u32,
    /// Its weight α·T at the pixel (0–1).
    pub weight: f32,
    pub record: AttributionRecord,
}

/// A watermarked scene with its attribution (and optionally its original), ready to draw.
pub struct Pictures {
    marked: Gaussians,
    original: Option<Gaussians>,
    /// The role and heatmap copies of `marked`, made on first use (a pick needs neither).
    roles: OnceLock<Gaussians>,
    heat: OnceLock<Gaussians>,
    records: Vec<AttributionRecord>,
    legend: Legend,
}

/// `g` with every Gaussian's view-independent colour set to `colour(i)` and its view-dependent
/// colour removed.
fn recoloured(g: &Gaussians, colour: impl Fn(usize) -> [f32; 3]) -> Gaussians {
    let mut c = g.clone();
    for i in 0..c.len() {
        c.sh_dc[i] = colour(i).map(|v| (v - 0.5) / SH_C0);
    }
    c.sh_rest.iter_mut().for_each(|v| *v = 0.0);
    c
}

/// A black → red → yellow → white ramp of `t` in [0, 1].
pub fn heat(t: f32) -> [f32; 3] {
    let t = t.clamp(0.0, 1.0) * 3.0;
    [
        t.min(1.0),
        (t - 1.0).clamp(0.0, 1.0),
        (t - 2.0).clamp(0.0, 1.0),
    ]
}

/// Every picture is drawn on black (the finetuning's background).
fn on_black() -> RenderOptions {
    RenderOptions {
        background: [0.0; 3],
        ..RenderOptions::default()
    }
}

impl Pictures {
    /// `records` in any order, one per Gaussian of `marked`.
    pub fn new(
        marked: Gaussians,
        mut records: Vec<AttributionRecord>,
        original: Option<Gaussians>,
    ) -> Result<Self, ExplainError> {
        records.sort_by_key(|r| r.index);
        if records.len() != marked.len()
            || records
                .iter()
                .enumerate()
                .any(|(i, r)| r.index as usize != i)
        {
            return Err(ExplainError::Mismatch {
                records: records.len(),
                gaussians: marked.len(),
            });
        }
        let shares: Vec<f32> = records
            .iter()
            .map(|r| r.wm_grad_share.unwrap_or(0.0))
            .collect();
        // White at the 99th percentile of the non-zero shares (a few Gaussians with most of the
        // gradient would otherwise leave the rest black).
        let mut nonzero: Vec<f32> = shares.iter().copied().filter(|&s| s > 0.0).collect();
        nonzero.sort_by(f32::total_cmp);
        let top = nonzero
            .get(nonzero.len().saturating_sub(1) * 99 / 100)
            .copied()
            .unwrap_or(1.0)
            .max(f32::MIN_POSITIVE);
        let count = |role: Role| records.iter().filter(|r| r.role == role).count();
        let (carriers, compensators) = (count(Role::Carrier), count(Role::Compensator));
        let legend = Legend {
            gaussians: marked.len(),
            carriers,
            compensators,
            untouched: marked.len() - carriers - compensators,
            carrier_share: records
                .iter()
                .zip(&shares)
                .filter(|(r, _)| r.role == Role::Carrier)
                .map(|(_, &s)| f64::from(s))
                .sum(),
            heat_white_at: top,
        };
        Ok(Self {
            marked,
            original,
            roles: OnceLock::new(),
            heat: OnceLock::new(),
            records,
            legend,
        })
    }

    /// Every Gaussian in its role's colour.
    fn roles(&self) -> &Gaussians {
        self.roles.get_or_init(|| {
            recoloured(&self.marked, |i| match self.records[i].role {
                Role::Carrier => CARRIER,
                Role::Compensator => COMPENSATOR,
                _ => UNTOUCHED,
            })
        })
    }

    /// Every Gaussian coloured by its share of the watermark gradient.
    fn heat(&self) -> &Gaussians {
        self.heat.get_or_init(|| {
            let top = self.legend.heat_white_at;
            recoloured(&self.marked, |i| {
                heat(self.records[i].wm_grad_share.unwrap_or(0.0) / top)
            })
        })
    }

    pub fn legend(&self) -> Legend {
        self.legend
    }

    pub fn has_original(&self) -> bool {
        self.original.is_some()
    }

    /// The layer through `cam`: linear RGB, row-major.
    pub fn draw(&self, layer: Layer, cam: &Camera) -> Result<Vec<[f32; 3]>, ExplainError> {
        let opts = on_black();
        Ok(match layer {
            Layer::View => render(&self.marked, cam, &opts)?.image,
            Layer::Roles => render(self.roles(), cam, &opts)?.image,
            Layer::Heat => render(self.heat(), cam, &opts)?.image,
            Layer::Diff => {
                let o = self.original.as_ref().ok_or(ExplainError::NoOriginal)?;
                let after = render(&self.marked, cam, &opts)?.image;
                let before = render(o, cam, &opts)?.image;
                after
                    .iter()
                    .zip(&before)
                    .map(|(p, q)| {
                        [0, 1, 2].map(|c| {
                            ((p[c].clamp(0.0, 1.0) - q[c].clamp(0.0, 1.0)).abs() * 10.0).min(1.0)
                        })
                    })
                    .collect()
            }
        })
    }

    /// The layer through `cam` as an 8-bit image.
    pub fn draw_rgb8(&self, layer: Layer, cam: &Camera) -> Result<image::RgbImage, ExplainError> {
        let px = self.draw(layer, cam)?;
        Ok(to_rgb8(cam.width, cam.height, &px))
    }

    /// The Gaussian pixel (`x`, `y`) of `cam` shows most (largest α·T), with its record; `None`
    /// where only the background is seen.
    pub fn pick(&self, cam: &Camera, x: u32, y: u32) -> Result<Option<Pick>, ExplainError> {
        if x >= cam.width || y >= cam.height {
            return Err(ExplainError::OutOfView {
                x,
                y,
                width: cam.width,
                height: cam.height,
            });
        }
        let replay = Replay::record(&self.marked, cam, &on_black())?;
        Ok(replay
            .strongest_at(x as usize, y as usize)
            .map(|(index, weight)| Pick {
                index,
                weight,
                record: self.records[index as usize].clone(),
            }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::embed::attribution::AttributionRecord;
    use glam::{Mat3, Vec3};

    fn record(index: u32, role: Role, share: f32) -> AttributionRecord {
        AttributionRecord {
            index,
            role,
            parent: index,
            child: 0,
            r: [0.5; 3],
            uncertainty: [0.1; 3],
            quality: [0.5; 3],
            utility: 0.5,
            visibility: 0.5,
            feasible: true,
            seed: None,
            mask_wm: [0.0; 5],
            mask_vis: [0.0; 5],
            wm_grad_share: Some(share),
        }
    }

    /// Two opaque Gaussians side by side in front of the camera, the left a carrier.
    fn two() -> (Gaussians, Camera) {
        let g = Gaussians {
            means: vec![[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]],
            log_scales: vec![[0.4f32.ln(); 3]; 2],
            rotations: vec![[1.0, 0.0, 0.0, 0.0]; 2],
            opacity_logits: vec![6.0; 2],
            sh_dc: vec![[0.5, 0.2, 0.1], [0.1, 0.2, 0.5]],
            sh_rest: vec![],
            sh_degree: 0,
        };
        // 64×32 pixels looking down +z at the pair from z = −2.5: centres at x = 24 and 40 px, σ 6.4 px.
        let cam = Camera::from_pose(
            "front",
            64,
            32,
            40.0,
            40.0,
            32.0,
            16.0,
            Mat3::IDENTITY,
            Vec3::new(0.0, 0.0, -2.5),
        );
        (g, cam)
    }

    #[test]
    fn a_pixel_picks_the_gaussian_it_shows_and_the_background_picks_none() {
        let (g, cam) = two();
        let recs = vec![
            record(0, Role::Carrier, 0.9),
            record(1, Role::Untouched, 0.1),
        ];
        let p = Pictures::new(g, recs, None).unwrap();
        let roles = p.draw(Layer::Roles, &cam).unwrap();
        let at = |x: usize, y: usize| roles[y * cam.width as usize + x];
        // The left half shows the carrier (red), the right half the untouched one (grey).
        let left = p.pick(&cam, 24, 16).unwrap().expect("a Gaussian");
        assert_eq!(left.index, 0);
        assert_eq!(left.record.role, Role::Carrier);
        assert!(at(24, 16)[0] > 2.0 * at(24, 16)[2], "{:?}", at(24, 16));
        let right = p.pick(&cam, 40, 16).unwrap().expect("a Gaussian");
        assert_eq!(right.index, 1);
        assert!(right.weight > 0.5, "{}", right.weight);
        assert!(
            p.pick(&cam, 0, 0).unwrap().is_none(),
            "a corner shows the background"
        );
        assert!(matches!(
            p.pick(&cam, 64, 0),
            Err(ExplainError::OutOfView { .. })
        ));
        assert_eq!(p.legend().carriers, 1);
        assert!((p.legend().carrier_share - 0.9).abs() < 1e-6);
    }

    #[test]
    fn records_of_another_scene_and_a_missing_original_are_refused() {
        let (g, cam) = two();
        assert!(matches!(
            Pictures::new(g.clone(), vec![record(0, Role::Carrier, 1.0)], None),
            Err(ExplainError::Mismatch { .. })
        ));
        let p = Pictures::new(
            g.clone(),
            vec![
                record(1, Role::Untouched, 0.0),
                record(0, Role::Carrier, 1.0),
            ],
            None,
        )
        .unwrap();
        assert!(matches!(
            p.draw(Layer::Diff, &cam),
            Err(ExplainError::NoOriginal)
        ));
        // With the original itself as the original, the difference is black.
        let p = Pictures::new(
            g.clone(),
            vec![
                record(0, Role::Carrier, 1.0),
                record(1, Role::Untouched, 0.0),
            ],
            Some(g),
        )
        .unwrap();
        let d = p.draw(Layer::Diff, &cam).unwrap();
        assert!(d.iter().all(|px| px.iter().all(|&v| v == 0.0)));
    }
}
