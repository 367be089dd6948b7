//! Tests of the whole embedding: the choice between the main and the coarse decoder.

use std::ops::ControlFlow;

use super::*;
use crate::scene::orbit::{OrbitOptions, orbit_cameras};
use crate::scene::synthetic::object_scene;

/// The decoders shipped for 32 bits (main and coarse) on the CPU, a small scene, its views
/// and a payload.
fn coarse_fixture() -> (Pair, Gaussians, Vec<Camera>, Vec<bool>) {
    let device = burn::tensor::Device::flex().autodiff();
    let pair = Pair::resolve(None, 32, &device).expect("shipped decoders");
    assert!(
        pair.coarse.is_some(),
        "a coarse decoder is shipped for 32 bits"
    );
    let g = object_scene(400, 0, 7);
    let cams = orbit_cameras(
        &g,
        &OrbitOptions {
            count: 6,
            width: 48,
            height: 48,
            ..OrbitOptions::default()
        },
    )
    .unwrap();
    let message: Vec<bool> = (0..32).map(|i| (i * 7 + 3) % 5 < 2).collect();
    (pair, g, cams, message)
}

fn small(margin: Option<f32>, target_psnr: f32) -> EmbedOptions {
    let mut o = EmbedOptions::default();
    o.finetune.steps = 10;
    o.finetune.stretch_bce = 0.0;
    o.finetune.target_psnr = target_psnr;
    o.coarse_margin_db = margin;
    o
}

#[test]
fn an_asset_with_fidelity_to_spare_is_written_for_the_coarse_decoder() {
    let (pair, g, cams, message) = coarse_fixture();
    let coarse = pair.coarse.clone().unwrap();
    let go = |pair: &Pair, o: &EmbedOptions| {
        let mut steps = Vec::new();
        let mut last = 0;
        let e = embed(&g, &cams, &message, pair, o, |p| {
            assert!(p.step >= last, "progress ran back from {last}: {p:?}");
            last = p.step;
            if p.log.is_some() {
                steps.push((p.step, p.total));
            }
            ControlFlow::Continue(())
        })
        .expect("embeds");
        (e, steps)
    };
    // A bound of 10 dB: every render is far above it, so the check (step 2 of 10) switches.
    let o = small(Some(2.0), 10.0);
    let (switched, steps) = go(&pair, &o);
    let c = switched.report.choice.expect("a choice was made");
    assert!(
        c.coarse && c.step == 2 && c.threshold == 12.0 && c.psnr > 12.0,
        "{c:?}"
    );
    assert_eq!(switched.report.decoder, coarse.digest());
    // Progress never runs backwards: the main decoder's steps up to the check, then the
    // coarse run's counted on from them.
    let totals: Vec<usize> = steps.iter().map(|s| s.1).collect();
    let steps: Vec<usize> = steps.iter().map(|s| s.0).collect();
    assert_eq!(steps, (1..=12).collect::<Vec<_>>());
    assert_eq!(
        totals,
        [10, 10].into_iter().chain([12; 10]).collect::<Vec<_>>()
    );
    // Stopping the job at the check is a cancellation, not a switch.
    let stopped = embed(&g, &cams, &message, &pair, &o, |p| {
        if p.phase == Phase::Finetune && p.step == 2 {
            ControlFlow::Break(())
        } else {
            ControlFlow::Continue(())
        }
    });
    assert!(matches!(stopped, Err(EmbedError::Cancelled)), "{stopped:?}");
    // The switch restarts from the original: the result is the coarse decoder's own
    // embedding at the coarse run's rate and bound, bit for bit, and so is what the report
    // says a dispute needs.
    let coarse_o = EmbedOptions {
        finetune: o.coarse_finetune(),
        ..o.clone()
    };
    let (alone, _) = go(&Pair::single(coarse.clone()), &coarse_o);
    assert!(alone.report.choice.is_none());
    assert_eq!(switched.scene, alone.scene);
    assert_eq!(
        switched.report.reference_logits,
        alone.report.reference_logits
    );
    assert_eq!(
        switched.report.view_projection,
        alone.report.view_projection
    );
    assert_eq!(
        pair.by_digest(&switched.report.decoder).map(|m| m.digest()),
        Some(coarse.digest())
    );

    // A bound the renders do not clear by the margin keeps the main decoder, and that
    // run is the main decoder's own embedding.
    let o = small(Some(60.0), 60.0);
    let (kept, _) = go(&pair, &o);
    let c = kept.report.choice.expect("a choice was made");
    assert!(!c.coarse && c.psnr <= c.threshold, "{c:?}");
    assert_eq!(kept.report.decoder, pair.main.digest());
    let (main_alone, _) = go(&Pair::single(pair.main.clone()), &o);
    assert_eq!(kept.scene, main_alone.scene);

    // Off, or without a bound to measure from: no choice, the main decoder.
    for o in [small(None, 38.0), small(Some(2.0), 0.0)] {
        let (e, _) = go(&pair, &o);
        assert_eq!(
            (e.report.choice, e.report.decoder.as_str()),
            (None, pair.main.digest().as_str())
        );
    }
    // A margin out of range is refused before anything runs.
    let e = embed(&g, &cams, &message, &pair, &small(Some(-1.0), 38.0), |_| {
        ControlFlow::Continue(())
    })
    .unwrap_err();
    assert!(e.to_string().contains("coarse_margin_db"), "{e}");
}

#[test]
fn a_switch_spends_the_free_budget_at_the_coarse_runs_rate_and_bound() {
    let (pair, g, cams, message) = coarse_fixture();
    let run = |o: &EmbedOptions| {
        embed(&g, &cams, &message, &pair, o, |_| ControlFlow::Continue(())).expect("embeds")
    };
    let mut same = small(Some(2.0), 30.0);
    same.coarse_wm_lr_factor = 1.0;
    same.coarse_bound_drop_db = 0.0;
    let mut harder = same.clone();
    harder.coarse_wm_lr_factor = 4.0;
    harder.coarse_bound_drop_db = 5.0;
    let (a, b) = (run(&same), run(&harder));
    // Both switched at the same check (the main runs are the same up to it).
    let (ca, cb) = (a.report.choice.unwrap(), b.report.choice.unwrap());
    assert!(ca.coarse && cb.coarse, "{ca:?} {cb:?}");
    assert_eq!((ca.step, ca.psnr), (cb.step, cb.psnr));
    // The report says what the coarse run ran at, and the log line names it.
    let rate = same.finetune.wm_lr_scale;
    assert_eq!(
        ca.coarse_run,
        Some(CoarseRun {
            wm_lr_scale: rate,
            target_psnr: 30.0
        })
    );
    assert_eq!(
        cb.coarse_run,
        Some(CoarseRun {
            wm_lr_scale: 4.0 * rate,
            target_psnr: 25.0
        })
    );
    assert!(cb.describe().contains("25.0 dB bound"), "{}", cb.describe());
    // Four times the rate writes harder: the watermark loss falls further and the renders
    // move further from the original.
    let (la, lb) = (a.log.last().unwrap(), b.log.last().unwrap());
    assert!(lb.l_wm < la.l_wm, "{la:?} {lb:?}");
    assert!(lb.psnr < la.psnr, "{la:?} {lb:?}");

    // Out of range, or a drop that takes the bound to 0: refused before anything runs.
    for (f, d, bound, what) in [
        (0.0, 0.0, 38.0, "coarse_wm_lr_factor"),
        (17.0, 0.0, 38.0, "coarse_wm_lr_factor"),
        (f32::NAN, 0.0, 38.0, "coarse_wm_lr_factor"),
        (1.0, -1.0, 38.0, "coarse_bound_drop_db"),
        (1.0, 21.0, 38.0, "coarse_bound_drop_db"),
        (1.0, 20.0, 20.0, "to 0 or below"),
    ] {
        let mut o = small(Some(2.0), bound);
        o.coarse_wm_lr_factor = f;
        o.coarse_bound_drop_db = d;
        let e = embed(
            &g,
            &cams,
            &message,
            &pair,
            &o,
            |_| ControlFlow::Continue(()),
        )
        .unwrap_err();
        assert!(e.to_string().contains(what), "{f} {d} {bound}: {e}");
    }
}
