//! Measurements on ../shared/data (ignored tests; docs/RESULTS.md):
//! - `removal_replay_gap`: how far the EOT term's removal — a replay recomposited without the
//!   removed Gaussians ([`crate::render::Replay::with_copies`]) — is from the attack itself (the
//!   scene rasterised with them gone), per shared scene.
//!
//! `cargo test --lib -- --ignored removal_replay_gap --nocapture`.

use super::*;
use crate::verify::bench::{QualityOptions, shared_scenes, views};

/// PSNR (dB) of `a` against `b` over the pixels `keep` selects.
fn psnr_where(a: &[[f32; 3]], b: &[[f32; 3]], keep: impl Fn(usize) -> bool) -> f64 {
    let (mut se, mut n) = (0.0f64, 0usize);
    for (i, (p, q)) in a.iter().zip(b).enumerate() {
        if keep(i) {
            for c in 0..3 {
                let d = f64::from(p[c].clamp(0.0, 1.0) - q[c].clamp(0.0, 1.0));
                se += d * d;
            }
            n += 3;
        }
    }
    if se == 0.0 {
        f64::INFINITY
    } else {
        10.0 * (n as f64 / se).log10()
    }
}

#[test]
#[ignore = "a measurement on ../shared/data (about a minute)"]
fn removal_replay_gap() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/scenes");
    if !dir.exists() {
        eprintln!("SKIP: {} is missing", dir.display());
        return;
    }
    let opts = QualityOptions::full(dir.clone());
    let ro = RenderOptions::default();
    for scene in shared_scenes() {
        let g = crate::scene::read_scene(dir.join(&scene.file), &crate::scene::Limits::default())
            .unwrap();
        let (train, _) = views(&scene, &g, &opts, 32).unwrap();
        let cams: Vec<_> = train
            .iter()
            .step_by(train.len() / 3)
            .take(3)
            .cloned()
            .collect();
        let vs = target_views(&g, &cams, &ro, &Rasterizer::Cpu).unwrap();
        let mut replayed = Renderer::new(&vs, &ro, true, Rasterizer::Cpu);
        let mut rasterised = Renderer::new(&vs, &ro, false, Rasterizer::Cpu);
        for (fraction, seed) in [(0.2f64, 1u64), (0.2, 2), (0.1, 3)] {
            let mut rng = crate::attack::diff::EotRng::new(seed);
            let removed: Vec<u8> = (0..g.len())
                .map(|_| u8::from(rng.uniform() >= fraction))
                .collect();
            for (v, view) in vs.iter().enumerate() {
                let a = replayed
                    .render_views_edited(&g, &[v], &removed)
                    .unwrap()
                    .remove(0);
                let b = rasterised
                    .render_views_edited(&g, &[v], &removed)
                    .unwrap()
                    .remove(0);
                let clean = &view.target;
                let asset = |i: usize| {
                    (0..3).any(|c| {
                        (clean[i][c] - ro.background[c]).abs() > 2.0 / 255.0
                            || (b.image()[i][c] - ro.background[c]).abs() > 2.0 / 255.0
                    })
                };
                let on_asset = (0..clean.len()).filter(|&i| asset(i)).count();
                let off = (0..clean.len())
                    .filter(|&i| {
                        (0..3).any(|c| (a.image()[i][c] - b.image()[i][c]).abs() > 2.0 / 255.0)
                    })
                    .count();
                eprintln!(
                    "{} view {v} ({}×{}), {:.0} % removed (seed {seed}): asset {:.1} % of the \
                     frame; the attack costs the asset {:.1} dB, the replay's removal {:.1} dB; \
                     replay against the attack: {:.1} dB on the asset, {:.1} % of its pixels \
                     off by > 2 levels",
                    scene.name,
                    view.camera.width,
                    view.camera.height,
                    fraction * 100.0,
                    100.0 * on_asset as f64 / clean.len() as f64,
                    psnr_where(b.image(), clean, asset),
                    psnr_where(a.image(), clean, asset),
                    psnr_where(a.image(), b.image(), asset),
                    100.0 * off as f64 / on_asset.max(1) as f64,
                );
            }
        }
    }
}
