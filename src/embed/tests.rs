//! Tests of SBAG (budget, visibility, selection, split invariance) and of the whole preparation,
//! including a smoke test on a real scene.

use super::attribution::{read_jsonl, write_jsonl};
use super::experts::{ExpertConfig, trio_experts};
use super::mask::{Route, apply_masks};
use super::sbag::*;
use super::*;
use crate::render::{ALPHA_MAX, ALPHA_MIN, RenderOptions, render};
use crate::scene::orbit::{OrbitOptions, orbit_cameras};
use crate::scene::synthetic::{Rng, object_scene};
use crate::scene::{Limits, logit, read_scene};
use glam::{Mat3, Vec3};
use std::path::PathBuf;

fn cams(g: &Gaussians, count: usize, size: u32) -> Vec<Camera> {
    orbit_cameras(
        g,
        &OrbitOptions {
            count,
            width: size,
            height: size,
            ..OrbitOptions::default()
        },
    )
    .unwrap()
}

// ---------------------------------------------------------------------------------------------
// Budget and visibility

#[test]
fn budget_formula_on_hand_computed_inputs() {
    // κ_eff = 0.02·0.4·0.5 = 0.004; B = ⌈32 / 0.004⌉ = 8000.
    let (k, b) = budget_size(32, 0.02, 0.4, 0.5);
    assert!((k - 0.004).abs() < 1e-9);
    assert_eq!(b, 8000);
    // κ_eff = 0.1·0.3·0.7 = 0.021; 48 / 0.021 = 2285.7 → 2286.
    let (k, b) = budget_size(48, 0.1, 0.3, 0.7);
    assert!((k - 0.021).abs() < 1e-8);
    assert_eq!(b, 2286);
    // 64 / (1·1·1) = 64 exactly: no rounding up.
    assert_eq!(budget_size(64, 1.0, 1.0, 1.0).1, 64);
    // Nothing visible: an unbounded budget (then capped by the feasible set).
    assert_eq!(budget_size(32, 0.02, 0.0, 0.5).1, usize::MAX);
}

fn ball(g: &mut Gaussians, mean: [f32; 3], scale: f32, o: f32) {
    g.means.push(mean);
    g.log_scales.push([scale.ln(); 3]);
    g.rotations.push([1.0, 0.0, 0.0, 0.0]);
    g.opacity_logits.push(logit(o));
    g.sh_dc.push([0.3, -0.2, 0.1]);
}

fn front_cam() -> Camera {
    Camera::from_pose(
        "front",
        64,
        64,
        80.0,
        80.0,
        32.0,
        32.0,
        Mat3::IDENTITY,
        Vec3::new(0.0, 0.0, -4.0),
    )
}

#[test]
fn eta_measures_overdraw_and_v_visibility() {
    let cfg = SbagConfig::default();
    // One half-transparent Gaussian: optical depth −ln(1 − α) ≤ ln 2 < 1 everywhere, so the
    // min never binds and η = 1.
    let mut one = Gaussians::with_capacity(0, 0);
    ball(&mut one, [0.0; 3], 0.3, 0.5);
    let v1 = visibility(&one, &[front_cam()], &cfg).unwrap();
    assert!((v1.eta - 1.0).abs() < 1e-5, "{}", v1.eta);

    // Six opaque Gaussians stacked: most pixels are covered many times over.
    let mut stack = Gaussians::with_capacity(0, 0);
    for k in 0..6 {
        ball(&mut stack, [0.0, 0.0, 0.1 * k as f32], 0.3, 0.95);
    }
    // And one far off screen: v = 0.
    ball(&mut stack, [50.0, 0.0, 0.0], 0.1, 0.9);
    let v6 = visibility(&stack, &[front_cam()], &cfg).unwrap();
    assert!(v6.eta < 0.5, "{}", v6.eta);
    assert!(v6.eta > 0.0);
    // Front to back the contributions fall; the off-screen one is invisible.
    let c = &v6.contribution;
    assert!(c.windows(2).take(5).all(|w| w[0] > w[1]), "{c:?}");
    assert_eq!(c[6], 0.0);
    assert_eq!(v6.v[6], 0.0);
    assert_eq!(v6.v[0], 1.0);
    // Hand check of η for the stack: Σ_p min(1, τ_p) / Σ_p τ_p with τ_p = −ln T_p.
    let r = render(
        &stack,
        &front_cam(),
        &RenderOptions {
            colors: Some(vec![[1.0f32; 3]; stack.len()].into()),
            ..Default::default()
        },
    )
    .unwrap();
    let (mut num, mut den) = (0.0f64, 0.0f64);
    for p in &r.image {
        let tau = -(1.0 - p[0] as f64).max(1e-12).ln();
        num += tau.min(1.0);
        den += tau;
    }
    assert!((v6.eta as f64 - num / den).abs() < 1e-5);
}

// ---------------------------------------------------------------------------------------------
// Split

/// Worst |ΔT| over a dense G grid of the scalar model (one parent, the renderer's α rules).
fn scalar_split_error(o: f64, carrier: f64, comp: f64, m: usize) -> f64 {
    let alpha = |a: f64, g: f64| {
        let x = (a * g).min(ALPHA_MAX);
        if x < ALPHA_MIN { 0.0 } else { x }
    };
    (0..=20000)
        .map(|k| {
            let g = k as f64 / 20000.0;
            let parent = 1.0 - alpha(o, g);
            let kids = (1.0 - alpha(carrier, g)) * (1.0 - alpha(comp, g)).powi(m as i32);
            (parent - kids).abs()
        })
        .fold(0.0, f64::max)
}

#[test]
fn compensator_opacity_keeps_the_scalar_model_within_tolerance() {
    let tol = 0.5 / 255.0;
    for n_split in [2usize, 3, 4] {
        let mut first = None;
        for k in 1..=1000 {
            let o = k as f32 / 1000.0;
            let Some(a) = compensator_opacity(o, n_split, tol) else {
                assert!(first.is_none(), "splittability is monotone in opacity");
                continue;
            };
            first.get_or_insert(o);
            assert!(a >= ALPHA_MIN as f32 && a <= o / n_split as f32);
            let e = scalar_split_error(o as f64, o as f64, a as f64, n_split - 1);
            assert!(
                e <= tol as f64 * 1.001,
                "N_s {n_split} o {o}: {}",
                e * 255.0
            );
        }
        // Opaque parents always split.
        assert!(first.unwrap() < 0.9, "{first:?}");
    }
    assert_eq!(compensator_opacity(0.3, 1, 0.0), Some(0.0));
    assert_eq!(compensator_opacity(0.3, 3, 0.5 / 255.0), None);
    // The even split 1 − (1 − o)^(1/N_s) is exact at the peak but far off in the tails.
    let o = 0.99f64;
    let oc = 1.0 - (1.0 - o).powf(1.0 / 3.0);
    let mut worst = 0.0f64;
    for k in 0..=1000 {
        let g = k as f64 / 1000.0;
        worst = worst.max(((1.0 - o * g) - (1.0 - oc * g).powi(3)).abs());
    }
    assert!(worst > 0.2, "{worst}");
}

/// A random scene like the renderer's tests: anisotropic, rotated, overlapping.
fn random_scene(rng: &mut Rng, n: usize, sh_degree: u8) -> Gaussians {
    let mut g = Gaussians::with_capacity(n, sh_degree);
    for _ in 0..n {
        g.means.push([
            rng.range(-0.7, 0.7),
            rng.range(-0.7, 0.7),
            rng.range(-0.7, 0.7),
        ]);
        g.log_scales.push([
            rng.range(-3.5, -1.8),
            rng.range(-3.5, -1.8),
            rng.range(-3.5, -1.8),
        ]);
        let q = [rng.normal(), rng.normal(), rng.normal(), rng.normal()];
        let l = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        g.rotations.push(q.map(|v| v / l));
        g.opacity_logits.push(rng.range(-2.0, 6.0));
        g.sh_dc.push([
            rng.range(-1.7, 1.7),
            rng.range(-1.7, 1.7),
            rng.range(-1.7, 1.7),
        ]);
        for _ in 0..g.rest_len() {
            g.sh_rest.push(0.15 * rng.normal());
        }
    }
    g
}

#[test]
fn split_renders_like_the_parent() {
    let tol = SbagConfig::default().split_tolerance;
    let mut worst = 0.0f32;
    let mut split_count = 0;
    for seed in 0..6u64 {
        let mut rng = Rng::new(100 + seed);
        let g = if seed % 2 == 0 {
            random_scene(&mut rng, 400, (seed % 4) as u8)
        } else {
            object_scene(3000, 1, seed)
        };
        // Split a random half of the splittable Gaussians, with 2, 3 or 4 children.
        let n_split = 2 + (seed % 3) as usize;
        let parents: Vec<u32> = (0..g.len() as u32)
            .filter(|&i| {
                compensator_opacity(g.opacity(i as usize), n_split, tol).is_some()
                    && rng.uniform() < 0.5
            })
            .collect();
        assert!(parents.len() > 30);
        split_count += parents.len();
        let s = split(&g, &parents, n_split, tol);
        assert_eq!(s.gaussians.len(), g.len() + parents.len() * (n_split - 1));
        let bg = [[0.0; 3], [1.0; 3], [0.2, 0.9, 0.4]][seed as usize % 3];
        let opts = RenderOptions {
            background: bg,
            ..Default::default()
        };
        let mut views = cams(&g, 5, 96);
        // Plus a close, tilted view so that footprints cover many pixels.
        views.push(Camera::from_pose(
            "close",
            120,
            90,
            150.0,
            150.0,
            61.0,
            44.0,
            Mat3::from_euler(glam::EulerRot::XYZ, 0.3, -0.2, 0.1),
            Vec3::new(0.2, -0.1, -2.2),
        ));
        for cam in &views {
            let a = render(&g, cam, &opts).unwrap();
            let b = render(&s.gaussians, cam, &opts).unwrap();
            assert_eq!(a.image.len(), b.image.len());
            for (p, q) in a.image.iter().zip(&b.image) {
                for ch in 0..3 {
                    worst = worst.max((p[ch] - q[ch]).abs());
                }
            }
        }
    }
    eprintln!(
        "split invariance: {split_count} parents, worst pixel change {:.3}/255",
        worst * 255.0
    );
    assert!(
        worst < 1.0 / 255.0,
        "worst pixel change {}/255",
        worst * 255.0
    );
}

#[test]
fn split_layout_roles_and_children() {
    let mut g = Gaussians::with_capacity(0, 1);
    for k in 0..4 {
        ball(&mut g, [k as f32, 0.0, 0.0], 0.1, 0.95);
        g.sh_rest.extend((0..9).map(|j| (k * 9 + j) as f32));
    }
    let s = split(&g, &[1, 3], 3, 0.5 / 255.0);
    assert_eq!(s.source, vec![0, 1, 1, 1, 2, 3, 3, 3]);
    assert_eq!(s.child, vec![0, 0, 1, 2, 0, 0, 1, 2]);
    use Role::*;
    assert_eq!(
        s.role,
        vec![
            Untouched,
            Carrier,
            Compensator,
            Compensator,
            Untouched,
            Carrier,
            Compensator,
            Compensator
        ]
    );
    let out = &s.gaussians;
    for (k, &src) in s.source.iter().enumerate() {
        let i = src as usize;
        assert_eq!(out.means[k], g.means[i]);
        assert_eq!(out.log_scales[k], g.log_scales[i]);
        assert_eq!(out.rotations[k], g.rotations[i]);
        assert_eq!(out.sh_dc[k], g.sh_dc[i]);
        assert_eq!(out.rest_of(k), g.rest_of(i));
        if s.role[k] == Compensator {
            let a = out.opacity(k);
            assert!(a > ALPHA_MIN as f32 && a < 0.02, "{a}");
        } else {
            assert_eq!(
                out.opacity_logits[k].to_bits(),
                g.opacity_logits[i].to_bits()
            );
        }
    }
    assert_eq!(s.is_carrier().iter().filter(|&&c| c).count(), 2);
    // N_s = 1: the carrier is the parent and nothing is added.
    let s1 = split(&g, &[0, 2], 1, 0.0);
    assert_eq!(s1.gaussians, g);
}

// ---------------------------------------------------------------------------------------------
// Selection

#[test]
fn selection_takes_top_b_of_the_feasible_set() {
    let g = object_scene(2000, 0, 3);
    let views = cams(&g, 6, 64);
    let scores = trio_experts(&g, &ExpertConfig::default());
    let cfg = SbagConfig::default();
    let vis = visibility(&g, &views, &cfg).unwrap();
    // M chosen so that B = 40 whatever v̄ and η are.
    let cfg = SbagConfig {
        kappa0: 1.0 / (vis.v_bar * vis.eta),
        ..cfg
    };
    let sel = select(&g, &scores, &vis, 40, &cfg);
    let b = &sel.budget;
    assert!((39..=41).contains(&b.b), "{b:?}");
    assert_eq!(b.wm0, b.b.min(b.feasible));
    assert!(sel.wm0.iter().all(|&i| sel.feasible[i as usize]));
    // Top-B: every feasible Gaussian left out has utility ≤ the worst selected one.
    let worst = sel
        .wm0
        .iter()
        .map(|&i| sel.u[i as usize])
        .fold(1.0, f32::min);
    for i in 0..g.len() {
        if sel.feasible[i] && !sel.wm0.contains(&(i as u32)) {
            assert!(sel.u[i] <= worst);
        }
    }
    // Feasible members pass every quantile and can be split.
    for i in (0..g.len()).filter(|&i| sel.feasible[i]) {
        assert!(compensator_opacity(g.opacity(i), 3, cfg.split_tolerance).is_some());
        assert!(vis.v[i] > 0.0);
    }
    // R and u follow eqs. rk_clip / ui_sym.
    for i in 0..g.len() {
        for k in 0..3 {
            let want = (scores.s[i][k] - cfg.beta * scores.u[i][k]).clamp(0.0, 1.0);
            assert_eq!(sel.r[i][k], want);
        }
        let r = sel.r[i];
        assert!((sel.u[i] - (r[0] * r[1] * r[2]).cbrt()).abs() < 1e-6);
    }
    // The extension adds at most 25 % and nothing twice.
    assert!(sel.prox.len() <= sel.wm0.len() / 4);
    assert_eq!(sel.parents.len(), sel.wm0.len() + sel.prox.len());
    assert!(sel.parents.windows(2).all(|w| w[0] < w[1]));
    assert!(sel.prox.iter().all(|p| !sel.wm0.contains(p)));

    // Fixed fraction: exactly ⌈f·N⌉ parents, topped up beyond 𝓕 when needed.
    for f in [0.01f32, 0.3] {
        let s = select(
            &g,
            &scores,
            &vis,
            40,
            &SbagConfig {
                mode: BudgetMode::Fraction(f),
                ..cfg.clone()
            },
        );
        let want = (f as f64 * 2000.0).ceil() as usize;
        assert_eq!(s.parents.len(), want.min(2000 - s.budget.unsplittable));
        assert_eq!(s.prox.len(), 0);
        if want > s.budget.feasible {
            assert_eq!(s.budget.outside_feasible, want - s.budget.feasible);
        }
    }
    // Random: as many parents as the adaptive run, deterministic per seed, not the same set.
    let rnd = |seed| {
        select(
            &g,
            &scores,
            &vis,
            40,
            &SbagConfig {
                mode: BudgetMode::Random { seed },
                ..cfg.clone()
            },
        )
    };
    let (r1, r2, r3) = (rnd(1), rnd(1), rnd(2));
    assert_eq!(r1.parents.len(), sel.parents.len());
    assert_eq!(r1.parents, r2.parents);
    assert_ne!(r1.parents, r3.parents);
    assert_ne!(r1.parents, sel.parents);
    assert!(
        r1.parents.iter().all(|&i| compensator_opacity(
            g.opacity(i as usize),
            3,
            cfg.split_tolerance
        )
        .is_some())
    );
}

#[test]
fn proximity_extension_recruits_look_alikes() {
    let g = object_scene(1500, 0, 4);
    let views = cams(&g, 6, 64);
    let scores = trio_experts(&g, &ExpertConfig::default());
    let vis = visibility(&g, &views, &SbagConfig::default()).unwrap();
    let cfg = SbagConfig {
        kappa0: 1.0 / (vis.v_bar * vis.eta),
        prox_cos: 0.9,
        prox_max_frac: 1.0,
        ..SbagConfig::default()
    };
    let sel = select(&g, &scores, &vis, 30, &cfg);
    assert!(!sel.prox.is_empty());
    let e = evidence_vectors(&scores, &vis, &sel.r, cfg.norm_q);
    let mut mu = [0.0f32; 6];
    for &i in &sel.wm0 {
        for c in 0..6 {
            mu[c] += e[i as usize][c] / sel.wm0.len() as f32;
        }
    }
    let cos = |i: usize| {
        let d: f32 = (0..6).map(|c| e[i][c] * mu[c]).sum();
        let n = |v: &[f32; 6]| v.iter().map(|x| x * x).sum::<f32>().sqrt();
        d / (n(&e[i]) * n(&mu))
    };
    let last = cos(*sel.prox.last().unwrap() as usize);
    assert!(last >= 0.9 - 1e-5);
    // Most similar first, and no eligible Gaussian more similar than the last recruit left out.
    assert!(
        sel.prox
            .windows(2)
            .all(|w| cos(w[0] as usize) >= cos(w[1] as usize) - 1e-6)
    );
    if sel.prox.len() < sel.wm0.len() {
        for i in 0..g.len() {
            let eligible = !sel.wm0.contains(&(i as u32))
                && sel.u[i] > 0.0
                && compensator_opacity(g.opacity(i), 3, cfg.split_tolerance).is_some();
            if eligible && cos(i) >= 0.9 + 1e-5 {
                assert!(sel.prox.contains(&(i as u32)), "{i} cos {}", cos(i));
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Whole preparation

#[test]
fn plan_is_consistent_end_to_end() {
    let g = object_scene(2500, 1, 9);
    let views = cams(&g, 6, 80);
    let cfg = EmbedConfig {
        prune: Some(Default::default()),
        ..Default::default()
    };
    let p = plan(&g, &views, 32, &cfg).unwrap();
    let rep = p.prune.as_ref().unwrap();
    let n = rep.kept.len();
    assert!(n > 1000 && n <= g.len());
    let split = &p.sbag.split;
    let parents = p.sbag.selection.parents.len();
    assert!(parents > 0);
    assert_eq!(p.scene().len(), n + 2 * parents);
    assert_eq!(p.records.len(), p.scene().len());
    let carriers: Vec<usize> = (0..p.scene().len())
        .filter(|&k| split.role[k] == Role::Carrier)
        .collect();
    assert_eq!(carriers.len(), parents);
    // Records point back to the upload and carry the masks of their route.
    for r in &p.records {
        let k = r.index as usize;
        let src = split.source[k] as usize;
        assert_eq!(r.parent as usize, rep.kept[src]);
        assert_eq!(g.means[r.parent as usize], p.scene().means[k]);
        assert_eq!(r.role, split.role[k]);
        match r.role {
            Role::Carrier => {
                assert_eq!(r.mask_wm, p.masks.wm_group);
                assert_eq!(r.mask_vis, [0.0; 5]);
                assert!(r.seed.is_some());
            }
            _ => {
                assert_eq!(r.mask_vis, p.masks.vis_group);
                assert_eq!(r.mask_wm, [0.0; 5]);
            }
        }
    }
    // The VIS floors hold, the caps hold.
    let mc = &cfg.mask;
    for c in 0..5 {
        assert!(p.masks.vis_group[c] >= mc.floor[c] && p.masks.vis_group[c] <= mc.cap[c]);
        assert!(p.masks.wm_group[c] >= 0.0 && p.masks.wm_group[c] <= mc.cap[c]);
    }
    // Gating a real gradient: a watermark pass leaves nothing on VIS.
    let cam = &views[0];
    let s32 = p.scene();
    let r = render(s32, cam, &RenderOptions::default()).unwrap();
    let ones = vec![[1.0f32; 3]; r.image.len()];
    let mut grad = crate::render::backward(s32, &r, &ones).unwrap().params;
    apply_masks(&mut grad, &p.masks, Route::Watermark);
    for k in 0..s32.len() {
        if split.role[k] != Role::Carrier {
            assert_eq!(grad.sh_dc[k], [0.0; 3]);
            assert_eq!(grad.opacity_logits[k], 0.0);
        }
        assert_eq!(grad.means[k], [0.0; 3]);
    }
    // JSON Lines round trip.
    let mut buf = Vec::new();
    write_jsonl(&p.records, &mut buf).unwrap();
    let text = String::from_utf8(buf.clone()).unwrap();
    assert_eq!(text.lines().count(), p.records.len());
    assert!(text.lines().next().unwrap().contains("\"role\":"));
    let back = read_jsonl(std::io::Cursor::new(buf)).unwrap();
    assert_eq!(back, p.records);
}

#[test]
fn planning_over_a_subset_of_the_views_prunes_over_all_of_them() {
    let g = object_scene(2500, 1, 9);
    let views = cams(&g, 6, 80);
    let cfg = EmbedConfig {
        prune: Some(Default::default()),
        ..Default::default()
    };
    let kept = |p: &Plan| p.prune.as_ref().unwrap().kept.clone();
    let all = plan(&g, &views, 32, &cfg).unwrap();
    let one = plan(&g, &views[..1], 32, &cfg).unwrap();
    // One view alone leaves Gaussians unseen that the others show: pruning them would cut
    // holes in the views the finetuning renders.
    assert!(kept(&one).len() < kept(&all).len());
    let over = plan_over(&g, &views, &views[..1], 32, &cfg).unwrap();
    assert_eq!(kept(&over), kept(&all));
    // Visibility, and so the carriers, from the one view.
    let pruned = subset(&g, &kept(&all));
    let one_view = visibility(&pruned, &views[..1], &cfg.sbag).unwrap();
    assert_eq!(over.sbag.visibility, one_view);
    assert_eq!(over.sbag.visibility.eta_per_view.len(), 1);
    assert_eq!(all.sbag.visibility.eta_per_view.len(), views.len());
}

#[test]
fn real_scene_smoke_donut() {
    let path = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/data/scenes/donut/fused.ply"
    ));
    if !path.is_file() {
        eprintln!("SKIPPED: real-data test, {} missing", path.display());
        return;
    }
    let t0 = std::time::Instant::now();
    let g = read_scene(&path, &Limits::default()).unwrap();
    let views = cams(&g, 8, 160);
    let scores = trio_experts(&g, &ExpertConfig::default());
    let t_exp = t0.elapsed().as_secs_f64();
    let cfg = SbagConfig::default();
    let res = sbag(&g, &scores, &views, 32, &cfg).unwrap();
    let b = &res.selection.budget;
    eprintln!(
        "donut: {} Gaussians, experts {:.2} s, total {:.2} s; budget {b:?}",
        g.len(),
        t_exp,
        t0.elapsed().as_secs_f64()
    );
    for v in scores.s.iter().chain(&scores.u) {
        assert!(v.iter().all(|x| (0.0..=1.0).contains(x)));
    }
    assert!(b.v_bar > 0.0 && b.v_bar < 1.0);
    assert!(b.eta > 0.0 && b.eta <= 1.0);
    assert!(b.b >= 1 && b.b < usize::MAX);
    assert!(b.feasible > 0 && b.feasible < g.len() / 2, "{b:?}");
    assert_eq!(b.wm0, b.b.min(b.feasible));
    assert!(b.parents >= b.wm0 && b.parents <= g.len() / 4, "{b:?}");
    assert_eq!(
        res.split.gaussians.len(),
        g.len() + b.parents * (cfg.n_split - 1)
    );
}

#[test]
#[ignore = "report: cargo test --lib real_scenes_budget_report -- --ignored --nocapture"]
fn real_scenes_budget_report() {
    let dir = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/data/scenes"
    ));
    for rel in [
        "donut/fused.ply",
        "plant/plant.splat",
        "udon/point_cloud.ply",
    ] {
        let path = dir.join(rel);
        if !path.is_file() {
            eprintln!("SKIPPED: {} missing", path.display());
            continue;
        }
        let t0 = std::time::Instant::now();
        let g = read_scene(&path, &Limits::default()).unwrap();
        let views = cams(&g, 12, 256);
        let cfg = EmbedConfig {
            prune: Some(Default::default()),
            ..Default::default()
        };
        let p = plan(&g, &views, 32, &cfg).unwrap();
        let b = &p.sbag.selection.budget;
        eprintln!(
            "{rel}: {} Gaussians, {} pruned, {:.1} s\n  {b:?}\n  masks wm {:?} vis {:?}",
            g.len(),
            p.prune.as_ref().unwrap().removed(),
            t0.elapsed().as_secs_f64(),
            p.masks.wm_group,
            p.masks.vis_group
        );
    }
}
