use super::*;
use crate::render::render;
use crate::scene::orbit::{OrbitOptions, orbit_cameras};
use crate::scene::synthetic::object_scene;

/// Renders of a synthetic object on white: `train` views on an orbit, `test` views between
/// them at another elevation (never trained on).
fn synthetic_dataset(train: usize, test: usize, size: u32) -> Dataset {
    let truth = object_scene(300, 1, 9);
    let views = |count: usize, elevations: Vec<f32>, offset: f32| -> Vec<View> {
        let opts = OrbitOptions {
            count,
            elevations_deg: elevations,
            width: size,
            height: size,
            azimuth_offset_deg: offset,
            ..OrbitOptions::default()
        };
        orbit_cameras(&truth, &opts)
            .unwrap()
            .into_iter()
            .map(|camera| {
                let ro = RenderOptions {
                    background: [1.0; 3],
                    ..RenderOptions::default()
                };
                let r = render(&truth, &camera, &ro).unwrap();
                let image = r
                    .image
                    .iter()
                    .map(|p| p.map(|c| c.clamp(0.0, 1.0)))
                    .collect();
                View { camera, image }
            })
            .collect()
    };
    Dataset::from_views(
        DatasetKind::Blender,
        views(train, vec![-20.0, 10.0, 35.0], 0.0),
        views(test, vec![20.0], 7.0),
        [1.0; 3],
        Init::RandomBox {
            min: [-1.3; 3],
            max: [1.3; 3],
        },
    )
    .unwrap()
}

fn small_config(iterations: usize) -> FitConfig {
    FitConfig {
        iterations,
        sh_degree: 1,
        sh_up_every: 100,
        init_points: 2_000,
        densify: DensifyConfig {
            from: 50,
            every: 50,
            opacity_reset_every: 150,
            ..DensifyConfig::default()
        },
        ..FitConfig::default()
    }
}

#[test]
fn a_fit_recovers_an_object_on_views_it_never_saw() {
    let ds = synthetic_dataset(24, 4, 64);
    let mut f = Fitter::new(&ds, small_config(600)).unwrap();
    let before = f.evaluate(&ds, &ds.test).unwrap();
    let mut densified = 0;
    for _ in 0..600 {
        let r = f.step(&ds).unwrap();
        assert!(r.loss.is_finite());
        densified += usize::from(r.densified.is_some());
    }
    let after = f.evaluate(&ds, &ds.test).unwrap();
    eprintln!(
        "test views: {before:?} → {after:?}, {} Gaussians",
        f.scene.len()
    );
    assert!(densified > 0);
    assert!(after.psnr > 24.0, "{after:?}");
    assert!(after.psnr > before.psnr + 8.0, "{before:?} → {after:?}");
    assert!(after.ssim > 0.9, "{after:?}");
    assert_eq!(f.active_sh_degree(), 1);
    // The output is a valid scene with unit quaternions.
    let out = f.output();
    out.validate().unwrap();
    assert!(
        out.rotations
            .iter()
            .all(|q| { (q.iter().map(|v| v * v).sum::<f32>() - 1.0).abs() < 1e-5 })
    );
}

#[test]
fn a_resumed_fit_is_bit_identical_to_an_uninterrupted_one() {
    let ds = synthetic_dataset(8, 1, 32);
    let cfg = FitConfig {
        init_points: 500,
        densify: DensifyConfig {
            from: 5,
            every: 10,
            opacity_reset_every: 25,
            ..DensifyConfig::default()
        },
        sh_up_every: 10,
        ..small_config(60)
    };
    let mut straight = Fitter::new(&ds, cfg.clone()).unwrap();
    for _ in 0..60 {
        straight.step(&ds).unwrap();
    }
    let mut first = Fitter::new(&ds, cfg).unwrap();
    for _ in 0..33 {
        first.step(&ds).unwrap();
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("fit.ckpt");
    checkpoint::save(&first, &path).unwrap();
    let mut resumed = checkpoint::load(&path, &ds).unwrap();
    assert_eq!(resumed, first);
    for _ in 33..60 {
        resumed.step(&ds).unwrap();
    }
    assert_eq!(resumed, straight);
    assert_eq!(
        checkpoint::to_bytes(&resumed),
        checkpoint::to_bytes(&straight)
    );
}

#[test]
fn checkpoints_of_other_data_or_damaged_ones_are_refused() {
    let ds = synthetic_dataset(4, 1, 16);
    let other = synthetic_dataset(5, 1, 16);
    let mut f = Fitter::new(&ds, small_config(10)).unwrap();
    f.step(&ds).unwrap();
    let bytes = checkpoint::to_bytes(&f);
    let err = checkpoint::from_bytes(&bytes, &other).unwrap_err();
    assert!(err.to_string().contains("another dataset"), "{err}");
    let mut damaged = bytes.clone();
    damaged[100] ^= 1;
    let err = checkpoint::from_bytes(&damaged, &ds).unwrap_err();
    assert!(err.to_string().contains("damaged"), "{err}");
    let err = checkpoint::from_bytes(&bytes[..50], &ds).unwrap_err();
    assert!(err.to_string().contains("checkpoint"), "{err}");
    // And a fitter refuses to step on another dataset.
    assert!(f.step(&other).is_err());
}

#[test]
fn bad_configurations_are_named() {
    let ds = synthetic_dataset(2, 1, 16);
    for (cfg, what) in [
        (
            FitConfig {
                iterations: 0,
                ..FitConfig::default()
            },
            "iterations",
        ),
        (
            FitConfig {
                sh_degree: 4,
                ..FitConfig::default()
            },
            "sh_degree",
        ),
        (
            FitConfig {
                lambda_dssim: 1.5,
                ..FitConfig::default()
            },
            "lambda_dssim",
        ),
        (
            FitConfig {
                lr: LearningRates {
                    opacity: f32::NAN,
                    ..LearningRates::default()
                },
                ..FitConfig::default()
            },
            "learning rates",
        ),
    ] {
        let err = Fitter::new(&ds, cfg).unwrap_err();
        assert!(err.to_string().contains(what), "{err}");
    }
}

#[test]
fn the_position_rate_decays_log_linearly_over_the_run() {
    let cfg = FitConfig {
        iterations: 1000,
        ..FitConfig::default()
    };
    assert!((cfg.position_rate(0) - 1.6e-4).abs() < 1e-9);
    assert!((cfg.position_rate(500) - 1.6e-5).abs() < 1e-9);
    assert!((cfg.position_rate(1000) - 1.6e-6).abs() < 1e-10);
    assert_eq!(cfg.densify_until(), 500);
}
