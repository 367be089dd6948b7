//! The finetuning on the GPU path against the CPU reference (lavapipe in CI): the rasterizer,
//! the decoder and the losses on the GPU's device, and the optimiser on the device.

use super::*;

#[test]
fn the_gpu_rasterizer_finetunes_as_the_cpu_reference_does() {
    // The same steps on both paths: colour only (replays on the CPU, rasterised on the GPU)
    // and with every channel moving (rasterised on both; removal in the EOT term).
    let gpu = crate::render::gpu::shared(crate::render::gpu::AdapterChoice::AllowSoftware)
        .unwrap_or_else(|e| {
            panic!("no wgpu adapter ({e}); `bash scripts/setup.sh` installs lavapipe")
        });
    let (g, views, _) = setup();
    let m = model(8);
    let msg = message();
    let mk = masks(g.len(), |_| true, [1.0; 5], [1.0; 5]);
    for (name, base) in [
        (
            "colour only",
            FinetuneConfig {
                target_psnr: 0.0,
                ..config(4)
            },
        ),
        (
            "every channel",
            FinetuneConfig {
                coupled: true,
                target_psnr: 0.0,
                eot_remove_probability: 0.5,
                lr: crate::embed::finetune::LearningRates::inria(),
                ..config(4)
            },
        ),
    ] {
        // With removal in the EOT term a removed Gaussian's step is L_vis's alone, and at a
        // render equal to its target that gradient is rounding (1e-19 in the host's closed
        // form, 1e-9 in burn's f32 graph on the device) which Adam's first steps amplify to a
        // full learning rate either way: the removal case starts away from its targets, so
        // that L_vis's gradient is real from the first step.
        let mut start = g.clone();
        if base.eot_remove_probability > 0.0 {
            for (i, c) in start.sh_dc.iter_mut().enumerate() {
                c[i % 3] += 0.05;
            }
        }
        let run = |rasterizer: crate::render::gpu::Rasterizer, m: &WatermarkModel| {
            let cams: Vec<_> = views.iter().map(|v| v.camera.clone()).collect();
            let views = target_views(&g, &cams, &RenderOptions::default(), &rasterizer).unwrap();
            let cfg = FinetuneConfig {
                rasterizer,
                ..base.clone()
            };
            finetune(&start, &mk, &views, m, &msg, &cfg, |_| {
                ControlFlow::Continue(())
            })
            .unwrap()
        };
        let gpu_rasterizer = crate::render::gpu::Rasterizer::Gpu(gpu.clone());
        let cpu = run(crate::render::gpu::Rasterizer::Cpu, &m);
        let on_gpu = run(gpu_rasterizer.clone(), &m);
        // And with the decoder, the losses and the attacks on the GPU's own device too.
        let on_device = m
            .clone()
            .to_device(&gpu_rasterizer.burn_device().unwrap().autodiff());
        let all_gpu = run(gpu_rasterizer, &on_device);
        assert!(!cpu.phases.images_on_device && !on_gpu.phases.images_on_device);
        assert!(
            all_gpu.phases.images_on_device,
            "{name}: the step's images left the GPU"
        );
        // Coupled steps by Adam: the Gaussians and their Adam state stay on the GPU too.
        assert_eq!(all_gpu.phases.params_on_device, base.coupled, "{name}");
        assert!(!on_gpu.phases.params_on_device);
        let moved: f32 = cpu
            .gaussians
            .sh_dc
            .iter()
            .zip(&start.sh_dc)
            .map(|(a, b)| (0..3).map(|c| (a[c] - b[c]).abs()).fold(0.0, f32::max))
            .fold(0.0, f32::max);
        // The largest gap per Gaussian, leaving out the worst 1 % of them: Adam's first steps
        // are ± a learning rate whatever a gradient's size, so a gradient at rounding level
        // (a Gaussian that barely reaches a pixel) may step either way when the two paths
        // sum in another order — burn's autotune picks the wgpu kernels by timing, and under
        // load picks others. Measured when they agree: gaps of 1.2e-7 (colours, of 0.04–0.17
        // moved) and 2e-9 (means).
        let gap = |a: &[[f32; 3]], b: &[[f32; 3]]| {
            let mut per: Vec<f32> = a
                .iter()
                .zip(b)
                .map(|(p, q)| (0..3).map(|c| (p[c] - q[c]).abs()).fold(0.0, f32::max))
                .collect();
            per.sort_by(f32::total_cmp);
            per[per.len() - 1 - per.len() / 100]
        };
        for (path, on_gpu) in [
            ("GPU rasterizer", &on_gpu),
            ("everything on the GPU", &all_gpu),
        ] {
            let dc_gap = gap(&cpu.gaussians.sh_dc, &on_gpu.gaussians.sh_dc);
            let mean_gap = gap(&cpu.gaussians.means, &on_gpu.gaussians.means);
            assert_eq!(cpu.log.len(), on_gpu.log.len());
            for (a, b) in cpu.log.iter().zip(&on_gpu.log) {
                assert!(
                    (a.l_wm - b.l_wm).abs() <= 1e-4 * a.l_wm.abs()
                        && (a.l_vis - b.l_vis).abs() <= 1e-4 * a.l_vis.abs().max(1e-6)
                        && (a.psnr == b.psnr || (a.psnr - b.psnr).abs() < 0.01),
                    "{name}, {path}, step {}: l_wm {} / {}, l_vis {} / {}, PSNR {} / {}",
                    a.step,
                    a.l_wm,
                    b.l_wm,
                    a.l_vis,
                    b.l_vis,
                    a.psnr,
                    b.psnr
                );
            }
            assert!(moved > 0.0, "{name}: nothing moved");
            // Rounding apart, the same trajectory.
            assert!(
                dc_gap < 1e-3 * moved,
                "{name}, {path}: colours moved {moved}, differ by {dc_gap}"
            );
            assert!(
                mean_gap < 1e-6,
                "{name}, {path}: means differ by {mean_gap}"
            );
        }
    }
}

#[test]
fn the_shipped_decoder_reads_every_eot_attack_alike_on_the_gpu_device() {
    // What a GPU worker runs each step on burn's wgpu runtime (the rasterizer's own device):
    // 8-bit rounding, the attack, the shipped decoder and the low-band term, forward and
    // backward to ∂L/∂image — against burn's CPU backend.
    let gpu = crate::render::gpu::shared(crate::render::gpu::AdapterChoice::AllowSoftware)
        .unwrap_or_else(|e| {
            panic!("no wgpu adapter ({e}); `bash scripts/setup.sh` installs lavapipe")
        });
    let on_gpu = crate::render::gpu::Rasterizer::Gpu(gpu)
        .burn_device()
        .unwrap()
        .autodiff();
    let on_cpu = Device::flex().autodiff();
    let cpu_model = WatermarkModel::shipped(32, &on_cpu).unwrap();
    assert_eq!(cpu_model.device(), Device::flex());
    let gpu_model = cpu_model.clone().to_device(&on_gpu);
    assert_ne!(gpu_model.device(), Device::flex());
    let (h, w) = (64, 80);
    let image: Vec<f32> = (0..3 * h * w)
        .map(|k| {
            let (c, y, x) = (k / (h * w), (k / w) % h, k % w);
            0.5 + 0.3 * ((x as f32 * 0.21 + c as f32).sin() * (y as f32 * 0.13).cos())
        })
        .collect();
    let target: Vec<f32> = image.iter().map(|v| v * 0.98 + 0.01).collect();
    let weights: Vec<f32> = (0..32)
        .map(|i| if i % 3 == 0 { 1.0 } else { -0.5 })
        .collect();
    let families = [
        AttackFamily::Noise { sigma: (0.1, 0.1) },
        AttackFamily::Blur {
            sigma: (0.8, 0.8),
            kernel: 3,
        },
        AttackFamily::Rotate { max_degrees: 30.0 },
        AttackFamily::Perspective { max_degrees: 20.0 },
        AttackFamily::Scale {
            factor: (0.75, 0.75),
        },
        AttackFamily::Crop { keep: (0.4, 0.4) },
        AttackFamily::Window { keep: (0.3, 0.5) },
        AttackFamily::Jpeg { quality: (50, 50) },
        AttackFamily::Brightness { factor: (0.9, 0.9) },
        AttackFamily::Contrast { factor: (1.1, 1.1) },
    ];
    let mut rng = EotRng::new(3);
    for family in families {
        let attack = family.sample(&mut rng).expect("not the identity");
        let run = |m: &WatermarkModel, device: &Device| {
            let x = Tensor::<4>::from_data(TensorData::new(image.clone(), [1, 3, h, w]), device)
                .require_grad();
            let t = Tensor::<4>::from_data(TensorData::new(target.clone(), [1, 3, h, w]), device);
            let (_, z, low, _) =
                decode_views(m, std::slice::from_ref(&x), &[t], Some(&attack), 2, None).unwrap();
            let wz = Tensor::<2>::from_data(TensorData::new(weights.clone(), [1, 32]), device);
            let grads = z[0].clone().mul(wz).sum().add(low).backward();
            let z: Vec<f32> = z[0].clone().detach().try_into_vec_as().unwrap();
            let d: Vec<f32> = x.grad(&grads).unwrap().try_into_vec_as().unwrap();
            (z, d)
        };
        let (z_cpu, d_cpu) = run(&cpu_model, &on_cpu);
        let (z_gpu, d_gpu) = run(&gpu_model, &on_gpu);
        let rel = |a: &[f32], b: &[f32]| {
            let (num, den) = a.iter().zip(b).fold((0.0f64, 0.0f64), |(n, d), (p, q)| {
                let (p, q) = (f64::from(*p), f64::from(*q));
                (n + (p - q) * (p - q), d + p * p)
            });
            (num / den.max(1e-30)).sqrt()
        };
        let (ez, ed) = (rel(&z_cpu, &z_gpu), rel(&d_cpu, &d_gpu));
        eprintln!("{}: logits {ez:.2e}, ∂L/∂image {ed:.2e}", attack.kind());
        assert!(
            d_cpu.iter().any(|v| *v != 0.0),
            "{}: the loss reaches the image",
            attack.kind()
        );
        assert!(
            ez < 1e-4 && ed < 1e-4,
            "{}: logits differ by {ez:.2e}, gradients by {ed:.2e} (relative L2)",
            attack.kind()
        );
    }
}

#[test]
fn the_device_optimiser_steps_as_the_host_one_does() {
    use crate::render::gpu::{AdapterChoice, StepPlan, shared};
    let gpu = shared(AdapterChoice::AllowSoftware).unwrap_or_else(|e| {
        panic!("no wgpu adapter ({e}); `bash scripts/setup.sh` installs lavapipe")
    });
    let (base, views, opts) = setup();
    let n = base.len();
    // Every channel moving at its own rate, half the Gaussians carriers, a third bounded.
    let mut rng = EotRng::new(5);
    let plan = StepPlan {
        rates: (0..n)
            .map(|i| {
                std::array::from_fn(|c| {
                    if (i + c) % 7 == 0 {
                        0.0
                    } else {
                        1e-3 * (1.0 + c as f32)
                    }
                })
            })
            .collect(),
        carrier: (0..n).map(|i| i % 2 == 0).collect(),
        bounded: (0..n).map(|i| i % 3 != 1).collect(),
    };
    let grads = |rng: &mut EotRng| {
        let mut g = base.cast(|_| 0.0f32);
        let mut r = |v: &mut f32| *v = (rng.uniform() as f32 - 0.5) * 0.02;
        g.means.iter_mut().flatten().for_each(&mut r);
        g.log_scales.iter_mut().flatten().for_each(&mut r);
        g.rotations.iter_mut().flatten().for_each(&mut r);
        g.opacity_logits.iter_mut().for_each(&mut r);
        g.sh_dc.iter_mut().flatten().for_each(&mut r);
        g.sh_rest.iter_mut().for_each(&mut r);
        g
    };
    let close = |what: &str, a: &Gaussians, b: &Gaussians| {
        for (i, (x, y)) in a.flat().iter().zip(b.flat()).enumerate() {
            assert!(
                (x - y).abs() <= 1e-6 * x.abs().max(1.0),
                "{what}, value {i}: host {x}, device {y}"
            );
        }
    };
    for coupled in [false, true] {
        let mut host = base.clone();
        let mut adam = Adam::new(&host);
        let mut dev = gpu.upload_params(&base, &base, &plan).unwrap();
        let mut norms = vec![0.0f64; n];
        for step in 0..3 {
            let (gw, gv) = (grads(&mut rng), grads(&mut rng));
            let wm_scale = 2.0 - 0.25 * step as f32;
            // The host's routing (`finetune`): coupled, both gradients on every Gaussian at the
            // watermark route's rates; decoupled, each Gaussian its own route's.
            let mut routed = gv.clone();
            if coupled {
                routed = gw.clone();
                add_into(&mut routed, &gv);
            } else {
                for i in 0..n {
                    if plan.carrier[i] {
                        copy_one(&mut routed, &gw, i);
                    }
                }
            }
            adam.step(&mut host, &routed, |i| {
                let s = if coupled || plan.carrier[i] {
                    wm_scale
                } else {
                    1.0
                };
                plan.rates[i].map(|r| r * s)
            });
            for (s, v) in norms.iter_mut().zip(grad_norms(&gw, step == 1)) {
                *s += f64::from(v);
            }
            let (dw, dv) = (
                gpu.upload_grads(&gw).unwrap(),
                gpu.upload_grads(&gv).unwrap(),
            );
            gpu.add_grad_norms(&dev, &dw, step == 1).unwrap();
            gpu.adam_step(&mut dev, &dw, &dv, coupled, wm_scale)
                .unwrap();
            close("Adam", &host, &gpu.read_params(&dev).unwrap());
        }
        assert_ne!(host.flat(), base.flat(), "nothing moved");
        for (i, (a, b)) in norms.iter().zip(gpu.read_norms(&dev).unwrap()).enumerate() {
            assert!(
                (*a as f32 - b).abs() <= 1e-5 * b.max(1e-3),
                "norm {i}: {a} vs {b}"
            );
        }
        // The fidelity bound's scaling of the bounded Gaussians' offsets.
        shrink_offsets(&mut host, &base, &plan.bounded, 0.6);
        gpu.shrink_offsets(&dev, 0.6).unwrap();
        let shrunk = gpu.read_params(&dev).unwrap();
        close("shrink", &host, &shrunk);
        for i in (0..n).filter(|&i| !plan.bounded[i]) {
            assert_eq!(shrunk.sh_dc[i], host.sh_dc[i]);
        }
        // A removal's edited copy renders as the host's; clones are refused on the device.
        let copies: Vec<u8> = (0..n).map(|i| u8::from(i % 4 != 0)).collect();
        let copy = gpu.params_edited(&dev, &copies).unwrap();
        let mut masked = shrunk.clone();
        for (o, &c) in masked.opacity_logits.iter_mut().zip(&copies) {
            if c == 0 {
                *o = -40.0;
            }
        }
        let cam = &views[0].camera;
        let a = gpu.render_uploaded(&copy, cam, &opts).unwrap();
        let b = gpu.render(&masked, cam, &opts).unwrap();
        let worst = a
            .image
            .iter()
            .zip(&b.image)
            .flat_map(|(p, q)| (0..3).map(move |c| (p[c] - q[c]).abs()))
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-4, "largest difference {worst}");
        let mut cloned = copies.clone();
        cloned[1] = 2;
        assert!(gpu.params_edited(&dev, &cloned).is_err());
        // Bad shapes are typed errors and change nothing.
        assert!(gpu.params_edited(&dev, &copies[1..]).is_err());
        let small = crate::scene::synthetic::object_scene(10, 1, 3);
        let other = gpu.upload_grads(&small).unwrap();
        assert!(
            gpu.adam_step(&mut dev, &other, &other, coupled, 1.0)
                .is_err()
        );
        assert_eq!(gpu.read_params(&dev).unwrap().flat(), shrunk.flat());
    }
}
