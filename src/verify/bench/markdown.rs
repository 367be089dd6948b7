//! The quality report as markdown tables.

use super::{QualityReport, QualityRun, TargetCheck};
use crate::verify::eval::Row;

/// The report as markdown tables (one row per scene × bits; accuracies in %).
pub fn markdown(report: &QualityReport) -> String {
    let cols = [
        "clean",
        "noise",
        "rotation",
        "scaling",
        "blur_0.8",
        "crop",
        "crop_on_asset",
        "jpeg",
        "combined",
        "combined_on_asset",
        "remove_20",
        "clone_20",
        "noise_0.1_scaled",
        "noise_0.1",
    ];
    let mut s = String::new();
    s += "| scene | bits | views train / unseen | PSNR | PSNR on the asset | SSIM |";
    for c in cols {
        s += &format!(" {c} |");
    }
    s += " clean detected per view | clean detected (avg logits) | unmarked detected | embed s (steps) | targets |\n";
    s += "|---|---|---|---|---|---|";
    for _ in cols {
        s += "---|";
    }
    s += "---|---|---|---|---|\n";
    for r in &report.runs {
        let acc = |name: &str| {
            r.eval
                .rows
                .iter()
                .find(|x| x.name == name)
                .map_or("–".to_string(), |x| {
                    format!("{:.1}", 100.0 * x.bit_accuracy)
                })
        };
        let row = |name: &str| r.eval.rows.iter().find(|x| x.name == name);
        let path = if r.path_views > 0 {
            format!(" + {} path", r.path_views)
        } else {
            String::new()
        };
        let on_asset = r
            .eval
            .psnr_on_asset
            .map_or("–".to_string(), |p| format!("{p:.2}"));
        s += &format!(
            "| {} | {} | {}{path} / {} | {:.2} | {on_asset} | {:.3} |",
            r.scene, r.bits, r.train_views, r.eval_views, r.eval.psnr, r.eval.ssim
        );
        for c in cols {
            s += &format!(" {} |", acc(c));
        }
        let missed: Vec<String> = r
            .targets
            .iter()
            .filter(|t| !t.met)
            .map(TargetCheck::describe)
            .collect();
        s += &format!(
            " {} | {} | {} | {:.0} ({}) | {} |\n",
            row("clean").map_or("–".into(), |x| format!(
                "{:.0} %",
                100.0 * x.detection_rate_per_view
            )),
            row("clean").map_or("–".into(), |x| format!(
                "{} (p {:.1e})",
                if x.detected { "yes" } else { "no" },
                x.p_value
            )),
            row("unmarked").map_or("–".into(), |x| if x.detected {
                "YES".into()
            } else {
                "no".to_string()
            }),
            r.embed_s,
            r.steps,
            if missed.is_empty() {
                "all met".to_string()
            } else {
                format!("missed: {}", missed.join(", "))
            }
        );
    }
    if report.runs.iter().any(|r| !r.eval.per_view.is_empty()) {
        s += "\nEach unseen view, clean (share of its pixels showing the asset · bits right, %; PSNR of the frame and of the asset's pixels; the share of the asset the 40 % crop keeps, centred and centred on the asset):\n\n";
        for r in report.runs.iter().filter(|r| !r.eval.per_view.is_empty()) {
            let views: Vec<String> = r
                .eval
                .per_view
                .iter()
                .map(|v| {
                    let crop = match (v.asset_in_crop, v.asset_in_crop_on_asset) {
                        (Some(k), Some(on)) => format!(
                            " (crop keeps {:.0} % of it, centred on it {:.0} %)",
                            100.0 * k,
                            100.0 * on
                        ),
                        (Some(k), None) => format!(" (crop keeps {:.0} % of it)", 100.0 * k),
                        _ => String::new(),
                    };
                    let psnr = match v.psnr_on_asset {
                        Some(p) => format!(" ({:.1} dB, on the asset {p:.1} dB)", v.psnr),
                        None => format!(" ({:.1} dB)", v.psnr),
                    };
                    format!(
                        "{:.0} % · {:.1}{psnr}{crop}",
                        100.0 * v.coverage,
                        100.0 * v.bit_accuracy
                    )
                })
                .collect();
            s += &format!("- {}, {} bits: {}\n", r.scene, r.bits, views.join("; "));
        }
    }
    s += &per_run(
        report,
        "The model attacks' bits right, % (the table's figure is the mean over the draws; the worst draw beside it, and the view that keeps the fewest bits over the draws):",
        |r, x| {
            (x.draws.len() > 1).then(|| {
                let weakest = x
                    .weakest_view()
                    .and_then(|(v, a)| Some((r.eval.per_view.get(v)?, a)))
                    .map_or(String::new(), |(v, a)| {
                        format!("; weakest view {} {:.1}", v.camera, 100.0 * a)
                    });
                format!(
                    "{} {:.1} (worst {:.1} of {}{weakest})",
                    x.name,
                    100.0 * x.bit_accuracy,
                    100.0 * x.worst_draw(),
                    x.draws.len()
                )
            })
        },
        |_| String::new(),
    );
    s += &per_run(
        report,
        "What each model attack costs the asset (PSNR of the attacked copy against the original, unseen views; the mean over the draws):",
        |_, x| {
            let frame = x.psnr_vs_original?;
            Some(match x.psnr_on_asset_vs_original {
                Some(a) => format!("{} {frame:.1} dB (on the asset {a:.1} dB)", x.name),
                None => format!("{} {frame:.1} dB", x.name),
            })
        },
        |r| {
            r.eval.noise_position_scale.map_or(String::new(), |k| {
                format!(" (scaled: the means' noise × {k:.3})")
            })
        },
    );
    s
}

/// A section of one line per run that has any: what `part` gives of each of the run's rows
/// (given the run and the row), then `tail` of the run; empty when no run has a part.
fn per_run(
    report: &QualityReport,
    heading: &str,
    part: impl Fn(&QualityRun, &Row) -> Option<String>,
    tail: impl Fn(&QualityRun) -> String,
) -> String {
    let lines: Vec<String> = report
        .runs
        .iter()
        .filter_map(|r| {
            let parts: Vec<String> = r.eval.rows.iter().filter_map(|x| part(r, x)).collect();
            (!parts.is_empty()).then(|| {
                format!(
                    "- {}, {} bits: {}{}",
                    r.scene,
                    r.bits,
                    parts.join("; "),
                    tail(r)
                )
            })
        })
        .collect();
    if lines.is_empty() {
        String::new()
    } else {
        format!("\n{heading}\n\n{}\n", lines.join("\n"))
    }
}
