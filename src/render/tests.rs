//! Tests of the rasterizer: exact values on hand-computable scenes and finite-difference checks
//! of every gradient (run in f64 so that the check is tight).

use super::*;
use crate::scene::{Camera, Gaussians};
use glam::{Mat3, Vec3};

/// A camera at `eye` looking at the origin-facing direction +z (identity rotation).
fn front_camera(w: u32, h: u32, f: f32, eye_z: f32) -> Camera {
    Camera::from_pose(
        "front",
        w,
        h,
        f,
        f,
        w as f32 / 2.0,
        h as f32 / 2.0,
        Mat3::IDENTITY,
        Vec3::new(0.0, 0.0, eye_z),
    )
}

fn one_gaussian(mean: [f64; 3], scale: f64, opacity_logit: f64, dc: [f64; 3]) -> Gaussians<f64> {
    Gaussians {
        means: vec![mean],
        log_scales: vec![[scale.ln(); 3]],
        rotations: vec![[1.0, 0.0, 0.0, 0.0]],
        opacity_logits: vec![opacity_logit],
        sh_dc: vec![dc],
        sh_rest: vec![],
        sh_degree: 0,
    }
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

#[test]
fn single_gaussian_matches_hand_computation() {
    // Isotropic Gaussian on the optical axis at depth 10, σ_world = 0.1, f = 100:
    // screen covariance = (f·s/z)² + 0.3 = 1 + 0.3 px², centred at (16, 16).
    let cam = front_camera(32, 32, 100.0, -10.0);
    let dc = [1.0, 0.0, -0.5];
    let g = one_gaussian([0.0, 0.0, 0.0], 0.1, 0.5, dc);
    let opts = RenderOptions {
        background: [0.2, 0.4, 0.6],
        ..Default::default()
    };
    let r = render(&g, &cam, &opts).unwrap();
    let o = sigmoid(0.5);
    let col: Vec<f64> = dc
        .iter()
        .map(|d| (0.282_094_791_773_878_1 * d + 0.5f64).max(0.0))
        .collect();
    #[allow(clippy::needless_range_loop)]
    for (py, px) in [(15usize, 15usize), (16, 16), (15, 17), (20, 15), (13, 19)] {
        let dx = px as f64 + 0.5 - 16.0;
        let dy = py as f64 + 0.5 - 16.0;
        let sigma = 0.5 * (dx * dx + dy * dy) / 1.3;
        let mut alpha = (o * (-sigma).exp()).min(0.99);
        if alpha < 1.0 / 255.0 {
            alpha = 0.0;
        }
        for ch in 0..3 {
            let want = col[ch] * alpha + (1.0 - alpha) * opts.background[ch] as f64;
            let got = r.image[py * 32 + px][ch];
            assert!(
                (got - want).abs() < 1e-9,
                "pixel ({px},{py}) ch {ch}: {got} vs {want}"
            );
        }
    }
    // Far from the Gaussian only the background remains.
    assert!((r.image[0][2] - 0.6).abs() < 1e-7);
    assert_eq!(r.stats.visible, 1);
}

#[test]
fn two_overlapping_gaussians_composite_front_to_back() {
    let cam = front_camera(32, 32, 100.0, -10.0);
    // Front Gaussian (depth 9) red, back Gaussian (depth 11) green, both centred on the axis.
    let mut g = one_gaussian([0.0, 0.0, 1.0], 0.1, 1.0, [1.0, -1.0, -1.0]);
    let back = one_gaussian([0.0, 0.0, -1.0], 0.1, 2.0, [-1.0, 1.0, -1.0]);
    g.means.insert(0, back.means[0]); // store back-to-front to check sorting
    g.log_scales.push(back.log_scales[0]);
    g.rotations.push(back.rotations[0]);
    g.opacity_logits.insert(0, back.opacity_logits[0]);
    g.sh_dc.insert(0, back.sh_dc[0]);
    let r = render(
        &g,
        &cam,
        &RenderOptions {
            blend_weights: true,
            ..Default::default()
        },
    )
    .unwrap();
    let (px, py) = (16usize, 16usize);
    let dx = px as f64 + 0.5 - 16.0;
    let s2_front = (100.0 * 0.1 / 11.0f64).powi(2) + 0.3; // wait: front is at depth 11? see below
    let _ = s2_front;
    // Camera at z = −10 looking +z: the Gaussian at z = −1 has depth 9 (front), z = +1 depth 11.
    let var_front = (100.0 * 0.1 / 9.0f64).powi(2) + 0.3;
    let var_back = (100.0 * 0.1 / 11.0f64).powi(2) + 0.3;
    let sig_f = 0.5 * 2.0 * dx * dx / var_front;
    let sig_b = 0.5 * 2.0 * dx * dx / var_back;
    let a_f = (sigmoid(2.0) * (-sig_f).exp()).min(0.99);
    let a_b = (sigmoid(1.0) * (-sig_b).exp()).min(0.99);
    let c = |d: f64| (0.282_094_791_773_878_1 * d + 0.5f64).max(0.0);
    // Front (index 0 after the inserts) is green, back (index 1) is red.
    let want_r = c(-1.0) * a_f + c(1.0) * a_b * (1.0 - a_f);
    let want_g = c(1.0) * a_f + c(-1.0) * a_b * (1.0 - a_f);
    let got = r.image[py * 32 + px];
    assert!((got[0] - want_r).abs() < 1e-9, "{} vs {want_r}", got[0]);
    assert!((got[1] - want_g).abs() < 1e-9, "{} vs {want_g}", got[1]);
    let w = r.blend_weights.unwrap();
    assert!(w[0] > w[1], "the front Gaussian takes more weight: {w:?}");
}

#[test]
fn behind_camera_and_off_screen_gaussians_are_culled() {
    let cam = front_camera(32, 32, 100.0, 0.0);
    let mut g = one_gaussian([0.0, 0.0, -1.0], 0.1, 2.0, [1.0; 3]); // behind
    let off = one_gaussian([50.0, 0.0, 5.0], 0.01, 2.0, [1.0; 3]); // far right of the frustum
    g.means.push(off.means[0]);
    g.log_scales.push(off.log_scales[0]);
    g.rotations.push(off.rotations[0]);
    g.opacity_logits.push(off.opacity_logits[0]);
    g.sh_dc.push(off.sh_dc[0]);
    let r = render(&g, &cam, &RenderOptions::default()).unwrap();
    assert_eq!(r.stats.visible, 0);
    assert!(r.image.iter().all(|p| p.iter().all(|&v| v == 0.0)));
}

#[test]
fn bad_camera_and_gradient_size_are_typed_errors() {
    let g = one_gaussian([0.0; 3], 0.1, 0.0, [0.0; 3]);
    let mut cam = front_camera(32, 32, 100.0, -10.0);
    cam.fx = f32::NAN;
    assert!(matches!(
        render(&g, &cam, &RenderOptions::default()),
        Err(RenderError::BadCamera { .. })
    ));
    let cam = front_camera(32, 32, 100.0, -10.0);
    let r = render(&g, &cam, &RenderOptions::default()).unwrap();
    assert!(matches!(
        backward(&g, &r, &[[0.0; 3]; 3]),
        Err(RenderError::GradientSize { .. })
    ));
}

/// A small deterministic random generator (tests must not depend on a crate's RNG stream).
struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    fn range(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * self.next()
    }
}

/// A random scene of `n` anisotropic, rotated Gaussians in front of a camera at the origin.
fn random_scene(rng: &mut Lcg, n: usize, sh_degree: u8) -> Gaussians<f64> {
    let rest = crate::scene::rest_len_for(sh_degree);
    let mut g = Gaussians {
        sh_degree,
        ..Default::default()
    };
    for _ in 0..n {
        g.means.push([
            rng.range(-0.6, 0.6),
            rng.range(-0.6, 0.6),
            rng.range(3.0, 5.0),
        ]);
        g.log_scales.push([
            rng.range(-2.6, -1.6),
            rng.range(-2.6, -1.6),
            rng.range(-2.6, -1.6),
        ]);
        g.rotations.push([
            rng.range(0.3, 1.0),
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
        ]);
        g.opacity_logits.push(rng.range(-1.5, 1.5));
        g.sh_dc.push([
            rng.range(-1.0, 1.5),
            rng.range(-1.0, 1.5),
            rng.range(-1.0, 1.5),
        ]);
        for _ in 0..rest {
            g.sh_rest.push(rng.range(-0.3, 0.3));
        }
    }
    g
}

fn fd_camera() -> Camera {
    // Slightly rotated camera so that every world axis mixes into the image.
    let rot = Mat3::from_euler(glam::EulerRot::XYZ, 0.1, -0.15, 0.05);
    Camera::from_pose(
        "fd",
        40,
        36,
        45.0,
        47.0,
        20.3,
        17.6,
        rot,
        Vec3::new(0.05, -0.04, 0.0),
    )
}

/// L = Σ_p w_p · image_p with fixed random weights.
fn loss(g: &Gaussians<f64>, cam: &Camera, opts: &RenderOptions, w: &[[f64; 3]]) -> f64 {
    let r = render(g, cam, opts).unwrap();
    r.image
        .iter()
        .zip(w)
        .map(|(p, q)| p[0] * q[0] + p[1] * q[1] + p[2] * q[2])
        .sum()
}

/// Compares every analytic gradient with a central finite difference (h = 1e-6, f64).
/// Tolerance: |analytic − fd| ≤ 1e-5 + 1e-4·|fd|.
fn check_gradients(seed: u64, n: usize, sh_degree: u8) {
    let mut rng = Lcg(seed);
    let g = random_scene(&mut rng, n, sh_degree);
    check_scene_gradients(&mut rng, g);
}

fn check_scene_gradients(rng: &mut Lcg, g: Gaussians<f64>) {
    let opts = RenderOptions {
        background: [0.3, 0.1, 0.7],
        ..Default::default()
    };
    check_scene_gradients_with(rng, g, &opts);
}

fn check_scene_gradients_with(rng: &mut Lcg, g: Gaussians<f64>, opts: &RenderOptions) {
    let n = g.len();
    let cam = fd_camera();
    let w: Vec<[f64; 3]> = (0..cam.width * cam.height)
        .map(|_| {
            [
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
            ]
        })
        .collect();
    let r = render(&g, &cam, opts).unwrap();
    assert_eq!(
        r.stats.visible, n,
        "every test Gaussian should be on screen"
    );
    let grads = backward(&g, &r, &w).unwrap().params;

    let h = 1e-6;
    let mut checked = 0;
    let mut fails = Vec::new();
    let mut check = |name: String, an: f64, set: &dyn Fn(&mut Gaussians<f64>, f64)| {
        let mut gp = g.clone();
        set(&mut gp, h);
        let mut gm = g.clone();
        set(&mut gm, -h);
        let fd = (loss(&gp, &cam, opts, &w) - loss(&gm, &cam, opts, &w)) / (2.0 * h);
        checked += 1;
        if (an - fd).abs() > 1e-5 + 1e-4 * fd.abs() {
            fails.push(format!("{name}: analytic {an:.8} fd {fd:.8}"));
        }
    };
    for i in 0..n {
        for a in 0..3 {
            check(format!("mean[{i}][{a}]"), grads.means[i][a], &|s, d| {
                s.means[i][a] += d
            });
            check(
                format!("log_scale[{i}][{a}]"),
                grads.log_scales[i][a],
                &|s, d| s.log_scales[i][a] += d,
            );
            check(format!("dc[{i}][{a}]"), grads.sh_dc[i][a], &|s, d| {
                s.sh_dc[i][a] += d
            });
        }
        for a in 0..4 {
            check(format!("rot[{i}][{a}]"), grads.rotations[i][a], &|s, d| {
                s.rotations[i][a] += d
            });
        }
        check(format!("opacity[{i}]"), grads.opacity_logits[i], &|s, d| {
            s.opacity_logits[i] += d
        });
        let rl = g.rest_len();
        for k in 0..rl {
            check(
                format!("rest[{i}][{k}]"),
                grads.sh_rest[i * rl + k],
                &|s, d| s.sh_rest[i * rl + k] += d,
            );
        }
    }
    assert!(
        fails.is_empty(),
        "{} of {checked} gradients disagree:\n{}",
        fails.len(),
        fails.join("\n")
    );
}

#[test]
fn gradients_match_finite_differences_sh0() {
    check_gradients(1, 6, 0);
}

#[test]
fn gradients_match_finite_differences_sh1() {
    check_gradients(2, 5, 1);
}

#[test]
fn gradients_match_finite_differences_sh3() {
    check_gradients(3, 5, 3);
}

#[test]
fn gradients_match_finite_differences_dense_overlap() {
    // Many overlapping Gaussians so that transmittance, early termination and the α clamp act.
    check_gradients(4, 24, 2);
}

#[test]
fn gradients_match_finite_differences_at_clamps() {
    // An opaque Gaussian whose centre reaches α = 0.99 (the clamp), and two large Gaussians
    // beyond 1.3× the field of view whose footprints still reach the image (Jacobian clamp).
    let mut rng = Lcg(11);
    let mut g = random_scene(&mut rng, 4, 1);
    let extra = [
        ([0.1, 0.05, 3.5], [-0.8, -0.9, -0.7], 8.0),
        ([2.6, 0.1, 4.0], [-0.3, -0.4, -0.5], 0.5),
        ([-0.2, -2.6, 4.0], [-0.5, -0.3, -0.4], 0.3),
    ];
    for (m, s, o) in extra {
        g.means.push(m);
        g.log_scales.push(s);
        g.rotations.push([0.9, 0.1, -0.2, 0.3]);
        g.opacity_logits.push(o);
        g.sh_dc.push([0.5, -0.2, 0.8]);
        g.sh_rest.extend((0..9).map(|_| rng.range(-0.3, 0.3)));
    }
    check_scene_gradients(&mut rng, g);
}

#[test]
fn forward_f32_agrees_with_f64() {
    let mut rng = Lcg(9);
    let g64 = random_scene(&mut rng, 30, 3);
    let g32 = g64.cast(|v| v as f32);
    let cam = fd_camera();
    let opts = RenderOptions::default();
    let a = render(&g64, &cam, &opts).unwrap();
    let b = render(&g32, &cam, &opts).unwrap();
    let max = a
        .image
        .iter()
        .zip(&b.image)
        .flat_map(|(p, q)| (0..3).map(move |c| (p[c] - q[c] as f64).abs()))
        .fold(0.0, f64::max);
    assert!(max < 1e-4, "f32 and f64 renders differ by {max}");
}

#[test]
fn blend_weights_agree_between_forward_and_backward() {
    let mut rng = Lcg(5);
    let g = random_scene(&mut rng, 12, 0);
    let cam = fd_camera();
    let opts = RenderOptions {
        blend_weights: true,
        ..Default::default()
    };
    let r = render(&g, &cam, &opts).unwrap();
    let zeros = vec![[0.0; 3]; r.image.len()];
    let b = backward(&g, &r, &zeros).unwrap();
    let f = r.blend_weights.as_ref().unwrap();
    for (x, y) in f.iter().zip(&b.blend_weights) {
        assert!((x - y).abs() < 1e-9 * (1.0 + x.abs()), "{x} vs {y}");
    }
    // Σ_i weights + Σ_p T_final = number of pixels (coverage is conserved).
    let total: f64 = f.iter().sum::<f64>()
        + r.state
            .final_t
            .iter()
            .enumerate()
            .filter(|(k, _)| {
                let t = k / (TILE * TILE);
                let [x0, y0, x1, y1] = r.state.tile_rect(t);
                let l = k % (TILE * TILE);
                let (lx, ly) = ((l % TILE) as u32, (l / TILE) as u32);
                x0 + lx < x1 && y0 + ly < y1
            })
            .map(|(_, t)| *t)
            .sum::<f64>();
    assert!((total - r.image.len() as f64).abs() < 1e-6, "{total}");
}

/// Every pixel against every Gaussian in depth order, with no tiles, bounding boxes or spans.
fn brute_force(g: &Gaussians<f64>, cam: &Camera, opts: &RenderOptions) -> Vec<[f64; 3]> {
    use super::project::{Cam, project};
    let c = Cam::<f64>::new(cam, opts.near);
    let mut ps: Vec<_> = (0..g.len())
        .filter_map(|i| project(g, i, &c, g.sh_degree))
        .collect();
    ps.sort_by(|a, b| a.tc[2].total_cmp(&b.tc[2]));
    let mut out = Vec::new();
    for py in 0..cam.height {
        for px in 0..cam.width {
            let (mut t, mut col) = (1.0, [0.0; 3]);
            for p in &ps {
                let dx = px as f64 + 0.5 - p.xy[0];
                let dy = py as f64 + 0.5 - p.xy[1];
                let [a, b, cc] = p.conic;
                let sigma = 0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy;
                let alpha = (p.opacity * (-sigma).exp()).min(ALPHA_MAX);
                if alpha < ALPHA_MIN {
                    continue;
                }
                if t * (1.0 - alpha) < T_MIN {
                    break;
                }
                for (c, pc) in col.iter_mut().zip(p.color) {
                    *c += pc * alpha * t;
                }
                t *= 1.0 - alpha;
            }
            out.push(std::array::from_fn(|ch| {
                col[ch] + t * opts.background[ch] as f64
            }));
        }
    }
    out
}

#[test]
fn tiled_render_equals_brute_force() {
    // Elongated, rotated Gaussians of all sizes across a non-multiple-of-16 image, so that
    // footprints cross tile borders diagonally and the per-band tile culling is exercised.
    let mut rng = Lcg(21);
    let mut g = random_scene(&mut rng, 300, 1);
    for (i, s) in g.log_scales.iter_mut().enumerate() {
        let k = (i % 5) as f64;
        *s = [-3.5 + 0.5 * k, -4.5 + rng.range(0.0, 1.0), -1.2 - 0.4 * k];
    }
    let cam = Camera::from_pose(
        "wide",
        83,
        61,
        60.0,
        60.0,
        41.0,
        30.0,
        Mat3::from_euler(glam::EulerRot::XYZ, 0.2, 0.1, 0.3),
        Vec3::new(0.0, 0.0, -0.5),
    );
    let opts = RenderOptions {
        background: [0.1, 0.2, 0.3],
        ..Default::default()
    };
    let r = render(&g, &cam, &opts).unwrap();
    let want = brute_force(&g, &cam, &opts);
    let mut max = 0.0f64;
    for (a, b) in r.image.iter().zip(&want) {
        for ch in 0..3 {
            max = max.max((a[ch] - b[ch]).abs());
        }
    }
    assert!(max < 1e-9, "tiled and brute-force renders differ by {max}");
    assert!(r.stats.visible > 200);
}

/// A random override colour on a 1/64 grid in [−0.5, 1.5): exact in f32, and so are ± 1/64.
fn dyadic_colors(rng: &mut Lcg, n: usize) -> Vec<[f32; 3]> {
    (0..n)
        .map(|_| std::array::from_fn(|_| (rng.range(-32.0, 96.0).floor() / 64.0) as f32))
        .collect()
}

#[test]
fn color_override_gradients_match_finite_differences() {
    // SH degree 1 so that an SH colour would depend on the means; with the override nothing may
    // flow into SH or through the view direction, and geometry gradients must still be right.
    let mut rng = Lcg(31);
    let g = random_scene(&mut rng, 8, 1);
    let colors = dyadic_colors(&mut rng, g.len());
    let opts = RenderOptions {
        background: [0.3, 0.1, 0.7],
        colors: Some(colors.clone().into()),
        ..Default::default()
    };
    check_scene_gradients_with(&mut rng, g.clone(), &opts);

    // ∂L/∂colour against central differences. L is linear in the colours and c ± 1/64 is exact
    // in f32, so the difference quotient is exact up to the f64 rounding of L.
    let cam = fd_camera();
    let w: Vec<[f64; 3]> = (0..cam.width * cam.height)
        .map(|_| std::array::from_fn(|_| rng.range(-1.0, 1.0)))
        .collect();
    let r = render(&g, &cam, &opts).unwrap();
    let grads = backward(&g, &r, &w).unwrap();
    assert!(grads.params.sh_dc.iter().flatten().all(|&v| v == 0.0));
    assert!(grads.params.sh_rest.iter().all(|&v| v == 0.0));
    let h = 1.0 / 64.0;
    for i in 0..g.len() {
        for ch in 0..3 {
            let with = |d: f32| {
                let mut c = colors.clone();
                c[i][ch] += d;
                let o = RenderOptions {
                    colors: Some(c.into()),
                    ..opts.clone()
                };
                loss(&g, &cam, &o, &w)
            };
            let fd = (with(h as f32) - with(-h as f32)) / (2.0 * h);
            let an = grads.colors[i][ch];
            assert!(
                (an - fd).abs() < 1e-10 * (1.0 + fd.abs()),
                "colour[{i}][{ch}]: analytic {an} fd {fd}"
            );
            assert!(an != 0.0, "every test Gaussian is on screen");
        }
    }
    // The colour gradient is the blend-weight-weighted image gradient: with ∂L/∂pixel = 1 in
    // every channel it equals Σ_p α_i T_i.
    let ones = vec![[1.0; 3]; r.image.len()];
    let gr = backward(&g, &r, &ones).unwrap();
    for (c, b) in gr.colors.iter().zip(&gr.blend_weights) {
        assert!(
            c.iter().all(|v| (v - b).abs() < 1e-12 * (1.0 + b)),
            "{c:?} vs {b}"
        );
    }
}

#[test]
fn color_override_equals_sh0_colour_and_checks_its_length() {
    // Colours in [0, 1] given as an override render exactly like SH degree 0 with
    // dc = (c − 0.5)/SH_C0, whatever the scene's SH degree.
    let mut rng = Lcg(32);
    let g = random_scene(&mut rng, 40, 2);
    let colors: Vec<[f32; 3]> = (0..g.len())
        .map(|_| std::array::from_fn(|_| rng.range(0.0, 1.0) as f32))
        .collect();
    let mut g0 = g.clone();
    g0.sh_degree = 0;
    g0.sh_rest.clear();
    for (dc, c) in g0.sh_dc.iter_mut().zip(&colors) {
        *dc = c.map(|v| (v as f64 - 0.5) / 0.282_094_791_773_878_1);
    }
    let cam = fd_camera();
    let base = RenderOptions {
        background: [0.2, 0.5, 0.9],
        blend_weights: true,
        ..Default::default()
    };
    let a = render(
        &g,
        &cam,
        &RenderOptions {
            colors: Some(colors.into()),
            ..base.clone()
        },
    )
    .unwrap();
    let b = render(&g0, &cam, &base).unwrap();
    for (p, q) in a.image.iter().zip(&b.image) {
        for ch in 0..3 {
            assert!((p[ch] - q[ch]).abs() < 1e-12, "{p:?} vs {q:?}");
        }
    }
    assert_eq!(a.blend_weights, b.blend_weights);
    let bad = RenderOptions {
        colors: Some(vec![[0.0; 3]; 3].into()),
        ..Default::default()
    };
    assert!(matches!(
        render(&g, &cam, &bad),
        Err(RenderError::BadScene(_))
    ));
}

/// A scene of `n` Gaussians dense enough that pixels see many of them, and a camera bigger than
/// one tile (so tiles, runs and the early stop at T ≤ 1e-4 are all exercised).
fn replay_scene(seed: u64, n: usize) -> (Gaussians<f32>, Camera) {
    let mut rng = Lcg(seed);
    let mut g = random_scene(&mut rng, n, 3).cast(|v| v as f32);
    for o in &mut g.opacity_logits {
        *o += 2.0; // opaque enough that some pixels stop early
    }
    let rot = Mat3::from_euler(glam::EulerRot::XYZ, 0.1, -0.15, 0.05);
    let cam = Camera::from_pose("replay", 70, 52, 60.0, 62.0, 35.2, 25.9, rot, Vec3::ZERO);
    (g, cam)
}

/// New colours for every Gaussian: DC and SH-rest moved, some channels pushed below the clamp.
fn recolour(g: &Gaussians<f32>, seed: u64) -> Gaussians<f32> {
    let mut rng = Lcg(seed);
    let mut h = g.clone();
    for dc in &mut h.sh_dc {
        for v in dc.iter_mut() {
            *v += rng.range(-3.0, 1.0) as f32;
        }
    }
    for v in &mut h.sh_rest {
        *v += rng.range(-0.2, 0.2) as f32;
    }
    h
}

#[test]
fn a_replay_renders_new_colours_bit_identically_to_the_rasterizer() {
    let (g, cam) = replay_scene(21, 400);
    let opts = RenderOptions {
        background: [0.1, 0.5, 0.9],
        ..Default::default()
    };
    let replay = Replay::record(&g, &cam, &opts).unwrap();
    assert_eq!(
        replay.render(&g).unwrap(),
        render(&g, &cam, &opts).unwrap().image
    );
    let h = recolour(&g, 5);
    let fresh = render(&h, &cam, &opts).unwrap().image;
    assert_ne!(fresh, render(&g, &cam, &opts).unwrap().image);
    assert_eq!(replay.render(&h).unwrap(), fresh);
    assert!(
        replay.contributions() > 70 * 52,
        "pixels see several Gaussians"
    );
}

#[test]
fn a_replays_colour_gradient_is_the_rasterizers_and_its_geometry_gradient_is_zero() {
    let (g, cam) = replay_scene(22, 300);
    let opts = RenderOptions::default();
    let h = recolour(&g, 6);
    let replay = Replay::record(&g, &cam, &opts).unwrap();
    let mut rng = Lcg(7);
    let d: Vec<[f32; 3]> = (0..70 * 52)
        .map(|_| std::array::from_fn(|_| rng.range(-1.0, 1.0) as f32))
        .collect();
    let ours = replay.backward(&h, &d).unwrap();
    let theirs = backward(&h, &render(&h, &cam, &opts).unwrap(), &d)
        .unwrap()
        .params;
    let (a, b): (Vec<f32>, Vec<f32>) = (
        ours.sh_dc
            .iter()
            .flatten()
            .chain(&ours.sh_rest)
            .copied()
            .collect(),
        theirs
            .sh_dc
            .iter()
            .flatten()
            .chain(&theirs.sh_rest)
            .copied()
            .collect(),
    );
    let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(scale > 0.1, "the loss reaches the colours");
    for (x, y) in a.iter().zip(&b) {
        assert!((x - y).abs() <= 1e-5 * scale, "{x} vs {y} (scale {scale})");
    }
    let geometry = ours
        .means
        .iter()
        .chain(&ours.log_scales)
        .flatten()
        .chain(ours.rotations.iter().flatten())
        .chain(&ours.opacity_logits);
    assert!(geometry.copied().all(|v| v == 0.0));
}

#[test]
fn a_replays_gradients_taken_together_are_each_taken_alone() {
    let (g, cam) = replay_scene(24, 300);
    let opts = RenderOptions::default();
    let h = recolour(&g, 9);
    let replay = Replay::record(&g, &cam, &opts).unwrap();
    let mut rng = Lcg(8);
    let mut d = || -> Vec<[f32; 3]> {
        (0..70 * 52)
            .map(|_| std::array::from_fn(|_| rng.range(-1.0, 1.0) as f32))
            .collect()
    };
    let (d1, d2) = (d(), d());
    let both = replay.backward_each(&h, &[&d1, &d2]).unwrap();
    assert_eq!(both.len(), 2);
    assert_eq!(both[0], replay.backward(&h, &d1).unwrap());
    assert_eq!(both[1], replay.backward(&h, &d2).unwrap());
    assert_ne!(both[0], both[1]);
    let short = vec![[0.0f32; 3]; 10];
    assert!(matches!(
        replay.backward_each(&h, &[&d1, &short]),
        Err(RenderError::GradientSize { got: 10, .. })
    ));
}

#[test]
fn a_replay_refuses_moved_geometry_colour_overrides_and_wrong_gradients() {
    let (g, cam) = replay_scene(23, 50);
    let opts = RenderOptions::default();
    let replay = Replay::record(&g, &cam, &opts).unwrap();
    let mut moved = g.clone();
    moved.means[7][0] += 1e-3;
    assert!(matches!(
        replay.render(&moved),
        Err(RenderError::BadScene(_))
    ));
    let mut faded = g.clone();
    faded.opacity_logits[3] -= 0.5;
    assert!(matches!(
        replay.backward(&faded, &vec![[0.0; 3]; 70 * 52]),
        Err(RenderError::BadScene(_))
    ));
    assert!(matches!(
        replay.backward(&g, &[[0.0; 3]; 10]),
        Err(RenderError::GradientSize { .. })
    ));
    let overridden = RenderOptions {
        colors: Some(vec![[0.5f32; 3]; g.len()].into()),
        ..Default::default()
    };
    assert!(matches!(
        Replay::record(&g, &cam, &overridden),
        Err(RenderError::BadScene(_))
    ));
}

/// A replay edited to hold `copies` of each Gaussian of a random scene (`copies_of` draws
/// them from uniform numbers), against the model attacks' own edit of the scene — the removed
/// ones gone, each clone appended as `ModelAttack::Clone` appends it — rasterised: the image
/// within `tol_image` and the colour gradient (a clone's added to its original's, the colour
/// being shared) within `tol_grad` of the largest, wherever the recorded render cannot have
/// stopped early (it stops before a Gaussian that would take T below 1e-4, so only where
/// T < 1e-4 / (1 − 0.99)): there, Gaussians it never reached show through a removed one's hole.
/// Returns the copies drawn.
fn check_replay_copies(
    seed: u64,
    copies_of: impl Fn(f64) -> u8,
    tol_image: f32,
    tol_grad: f32,
) -> Vec<u8> {
    let (g, cam) = replay_scene(seed, 400);
    let opts = RenderOptions {
        background: [0.2, 0.4, 0.8],
        ..Default::default()
    };
    let replay = Replay::record(&g, &cam, &opts).unwrap();
    let mut rng = Lcg(seed + 1);
    let copies: Vec<u8> = (0..g.len())
        .map(|_| copies_of(rng.range(0.0, 1.0)))
        .collect();
    let mut idx: Vec<usize> = (0..g.len()).filter(|&i| copies[i] > 0).collect();
    idx.extend(
        (0..g.len()).flat_map(|i| std::iter::repeat_n(i, usize::from(copies[i].saturating_sub(1)))),
    );
    let attacked = crate::embed::subset(&g, &idx);
    let truth = render(&attacked, &cam, &opts).unwrap();
    let edited = replay.with_copies(&copies).unwrap();
    let ours = edited.render(&g).unwrap();
    let before = replay.render(&g).unwrap();
    let moved = before
        .iter()
        .zip(&truth.image)
        .filter(|(a, b)| (0..3).any(|c| (a[c] - b[c]).abs() > 1e-3))
        .count();
    assert!(moved > 500, "the edit changes the view ({moved} pixels)");
    let full = render(&g, &cam, &opts).unwrap();
    let tiles_x = 70usize.div_ceil(TILE);
    let stopped = |i: usize| {
        let (x, y) = (i % 70, i / 70);
        let k = ((y / TILE) * tiles_x + x / TILE) * TILE * TILE + (y % TILE) * TILE + x % TILE;
        full.state.final_t[k] < 1e-2
    };
    let n_stopped = (0..70 * 52).filter(|&i| stopped(i)).count();
    assert!(
        n_stopped > 0 && n_stopped < 70 * 52 / 4,
        "{n_stopped} pixels stopped early"
    );
    let worst = ours
        .iter()
        .zip(&truth.image)
        .enumerate()
        .filter(|&(i, _)| !stopped(i))
        .flat_map(|(_, (a, b))| (0..3).map(move |c| (a[c] - b[c]).abs()))
        .fold(0.0f32, f32::max);
    assert!(worst < tol_image, "largest difference {worst}");
    let d: Vec<[f32; 3]> = (0..70 * 52)
        .map(|i| {
            let d = std::array::from_fn(|_| rng.range(-1.0, 1.0) as f32);
            if stopped(i) { [0.0; 3] } else { d }
        })
        .collect();
    let a = edited.backward(&g, &d).unwrap();
    let b = backward(&attacked, &truth, &d).unwrap().params;
    let mut summed = vec![[0.0f32; 3]; g.len()];
    for (&i, dc) in idx.iter().zip(&b.sh_dc) {
        for (s, v) in summed[i].iter_mut().zip(dc) {
            *s += v;
        }
    }
    let scale = summed.iter().flatten().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(scale > 0.1);
    for (i, (x, y)) in a.sh_dc.iter().zip(&summed).enumerate() {
        for c in 0..3 {
            assert!(
                (x[c] - y[c]).abs() <= tol_grad * scale,
                "Gaussian {i} ({} copies): {} vs {}",
                copies[i],
                x[c],
                y[c]
            );
        }
        if copies[i] == 0 {
            assert_eq!(*x, [0.0; 3]);
        }
    }
    assert!(matches!(
        replay.with_copies(&copies[1..]),
        Err(RenderError::BadScene(_))
    ));
    copies
}

#[test]
fn a_replay_without_some_gaussians_renders_and_differentiates_as_the_scene_without_them() {
    let copies = check_replay_copies(25, |x| u8::from(x >= 0.2), 1e-4, 1e-4);
    assert!(copies.iter().filter(|&&c| c == 0).count() > 40);
    // `without` is the same edit.
    let (g, cam) = replay_scene(25, 400);
    let replay = Replay::record(&g, &cam, &RenderOptions::default()).unwrap();
    let dropped: Vec<bool> = copies.iter().map(|&c| c == 0).collect();
    assert_eq!(
        replay.without(&dropped).unwrap().render(&g).unwrap(),
        replay.with_copies(&copies).unwrap().render(&g).unwrap()
    );
    assert!(matches!(
        replay.without(&dropped[1..]),
        Err(RenderError::BadScene(_))
    ));
}

#[test]
fn a_replay_with_copies_renders_and_differentiates_as_the_scene_with_its_clones() {
    let copies = check_replay_copies(
        27,
        |x| match x {
            x if x < 0.1 => 0,
            x if x < 0.3 => 2,
            _ => 1,
        },
        2e-4,
        1e-3,
    );
    assert!(copies.contains(&0) && copies.contains(&2));
}
