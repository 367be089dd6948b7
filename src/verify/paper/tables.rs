//! The markdown of `bench paper`: our rows beside the paper's published rows (copied from
//! `../shared/paper/`) for Tables 1, 2, 3, 5 and 6, each cell the mean ± std over seeds.

use super::{PaperReport, PaperRun};

/// Mean and standard deviation (population; 0 for one value) of `xs`, `None` when empty.
fn mean_std(xs: &[f64]) -> Option<(f64, f64)> {
    if xs.is_empty() {
        return None;
    }
    let n = xs.len() as f64;
    let m = xs.iter().sum::<f64>() / n;
    let v = xs.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n;
    Some((m, v.sqrt()))
}

/// A metric of a run: "psnr", "ssim", or a row's bit accuracy in %.
fn metric(r: &PaperRun, what: &str) -> Option<f64> {
    match what {
        "psnr" => Some(r.eval.psnr),
        "ssim" => Some(r.eval.ssim),
        "storage_mb" => Some(r.storage_bytes as f64 / 1e6),
        row => r
            .eval
            .rows
            .iter()
            .find(|x| x.name == row)
            .map(|x| 100.0 * x.bit_accuracy),
    }
}

/// "mean ± std" over the runs that `pick` selects, or "–".
fn cell(runs: &[PaperRun], pick: impl Fn(&PaperRun) -> bool, what: &str, digits: usize) -> String {
    let xs: Vec<f64> = runs
        .iter()
        .filter(|r| pick(r))
        .filter_map(|r| metric(r, what))
        .collect();
    match mean_std(&xs) {
        None => "–".into(),
        Some((m, _)) if xs.len() == 1 => format!("{m:.digits$}"),
        Some((m, s)) => format!("{m:.digits$} ± {s:.digits$}"),
    }
}

/// Table 1 as published (bit acc, PSNR, SSIM, LPIPS at 32 / 48 / 64 bits).
const PUBLISHED_T1: [(&str, [f64; 12]); 4] = [
    (
        "WateRF+3D-GS",
        [
            93.28, 30.57, 0.954, 0.052, 84.39, 30.06, 0.949, 0.056, 74.92, 25.73, 0.887, 0.105,
        ],
    ),
    (
        "GuardSplat",
        [
            95.58, 35.32, 0.978, 0.043, 93.29, 33.36, 0.969, 0.045, 90.14, 32.25, 0.963, 0.048,
        ],
    ),
    (
        "3D-GSW",
        [
            97.22, 35.15, 0.977, 0.044, 93.59, 33.26, 0.972, 0.047, 91.31, 32.52, 0.966, 0.050,
        ],
    ),
    (
        "paper (Ours)",
        [
            98.46, 35.98, 0.982, 0.041, 94.29, 33.45, 0.973, 0.044, 91.65, 32.71, 0.969, 0.047,
        ],
    ),
];

/// Table 2 as published: clean, noise, rotation, scaling, blur, crop, JPEG, combined.
const PUBLISHED_T2: [(&str, [f64; 8]); 4] = [
    (
        "WateRF+3D-GS",
        [93.28, 78.12, 81.47, 84.63, 87.09, 84.58, 82.03, 64.73],
    ),
    (
        "GuardSplat",
        [95.58, 90.11, 95.87, 94.93, 97.16, 95.05, 89.92, 88.64],
    ),
    (
        "3D-GSW",
        [97.22, 83.71, 88.05, 94.58, 95.94, 92.73, 92.54, 90.96],
    ),
    (
        "paper (Ours)",
        [98.46, 91.22, 96.18, 95.06, 97.75, 95.88, 92.95, 91.30],
    ),
];

/// Table 3 as published: clean, parameter noise, remove 20 %, clone 20 %.
const PUBLISHED_T3: [(&str, [f64; 4]); 4] = [
    ("WateRF+3D-GS", [93.28, 62.35, 60.91, 76.16]),
    ("GuardSplat", [95.58, 79.96, 88.49, 92.30]),
    ("3D-GSW", [97.22, 89.93, 97.23, 96.85]),
    ("paper (Ours)", [98.46, 90.52, 98.16, 97.48]),
];

/// Table 5 as published: (SBAG, mask, decoupling) → bit acc, PSNR, SSIM, LPIPS.
const PUBLISHED_T5: [(&str, [f64; 4]); 5] = [
    ("paper_none", [94.70, 30.00, 0.952, 0.073]),
    ("paper_no_decoupling", [96.80, 34.10, 0.974, 0.048]),
    ("paper_no_mask", [97.10, 33.70, 0.972, 0.051]),
    ("paper_no_sbag", [95.10, 33.10, 0.968, 0.056]),
    ("paper", [97.80, 35.20, 0.979, 0.042]),
];

/// Table 6 as published: budget → bit acc, PSNR, SSIM, LPIPS, storage (MB).
const PUBLISHED_T6: [(&str, [f64; 5]); 3] = [
    ("paper_budget_1%", [97.19, 34.98, 0.980, 0.046, 164.0]),
    ("paper", [98.46, 35.98, 0.982, 0.041, 178.0]),
    ("paper_budget_10%", [98.12, 34.24, 0.975, 0.048, 195.0]),
];

const IMAGE_COLS: [(&str, &str); 8] = [
    ("clean", "No distortion"),
    ("noise", "Noise σ 0.1"),
    ("rotation", "Rotation ±π/6"),
    ("scaling", "Scaling 75 %"),
    ("blur", "Blur σ 0.1"),
    ("crop", "Crop 40 %"),
    ("jpeg", "JPEG 50"),
    ("combined", "Combined"),
];

const MODEL_COLS: [(&str, &str); 4] = [
    ("clean", "No distortion"),
    ("noise_0.1", "Parameter noise σ 0.1"),
    ("remove_20", "Remove 20 %"),
    ("clone_20", "Clone 20 %"),
];

/// The report as markdown: Tables 1, 2, 3, 5 and 6 with the published rows beside ours.
pub fn markdown(report: &PaperReport) -> String {
    let runs = &report.runs;
    let mut s = String::new();
    let datasets: Vec<&str> = report.options.datasets.iter().map(String::as_str).collect();
    let seeds = report.options.seeds.len();
    s += &format!(
        "Our rows: splatmark on scenes fitted here, evaluated on each dataset's test views \
         ({}); {}. Published rows: the paper's (Blender, LLFF and Mip-NeRF 360 averaged). \
         LPIPS: not measured (no pretrained LPIPS loads without a download).\n\n",
        datasets.join(", "),
        if seeds == 1 {
            "one seed".to_string()
        } else {
            format!("mean ± std over {seeds} seeds")
        }
    );
    s += "**Fits**\n\n| dataset | views train / test | size | steps | Gaussians | test PSNR | test SSIM | fit s |\n|---|---|---|---|---|---|---|---|\n";
    for f in &report.fits {
        s += &format!(
            "| {} | {} / {} | {}×{} | {} | {} | {:.2} | {:.4} | {:.0}{} |\n",
            f.name,
            f.train_views,
            f.test_views,
            f.width,
            f.height,
            f.config.iterations,
            f.gaussians,
            f.test.psnr,
            f.test.ssim,
            f.seconds,
            if f.cached { " (cached)" } else { "" }
        );
    }
    if report.options.view_scale != 1.0 {
        s += &format!(
            "\nEmbedded and evaluated at ×{} of the fits' resolution (a cheaper run than the \
             protocol's).\n",
            report.options.view_scale
        );
    }
    s += "\n**Runs** (seconds on this machine; a reused run keeps the time it took)\n\n\
          | dataset | variant | bits | seed | views train / test | size | embed s | eval s | \
          test PSNR | clean bit acc |\n|---|---|---|---|---|---|---|---|---|---|\n";
    for r in runs {
        s += &format!(
            "| {} | {} | {} | {} | {} / {} | {}×{} | {:.0} | {:.0} | {:.2} | {} |\n",
            r.dataset,
            r.variant,
            r.bits,
            r.seed,
            r.train_views,
            r.test_views,
            r.width,
            r.height,
            r.embed_s,
            r.eval_s,
            r.eval.psnr,
            cell(std::slice::from_ref(r), |_| true, "clean", 2)
        );
    }

    // Table 1.
    s += "\n**Table 1: bit accuracy and rendering quality (test views)**\n\n| method |";
    for b in [32, 48, 64] {
        s += &format!(" {b}: bit acc | PSNR | SSIM | LPIPS |");
    }
    s += "\n|---|";
    s += &"---|".repeat(12);
    s += "\n";
    for (name, v) in PUBLISHED_T1 {
        s += &format!("| {name} |");
        for c in v.chunks(4) {
            s += &format!(" {:.2} | {:.2} | {:.3} | {:.3} |", c[0], c[1], c[2], c[3]);
        }
        s += "\n";
    }
    let mut ours_row = |label: String, pick: &dyn Fn(&PaperRun) -> bool| {
        let mut row = format!("| {label} |");
        for b in [32, 48, 64] {
            let p = |r: &PaperRun| pick(r) && r.variant == "default" && r.bits == b;
            row += &format!(
                " {} | {} | {} | n/a |",
                cell(runs, p, "clean", 2),
                cell(runs, p, "psnr", 2),
                cell(runs, p, "ssim", 3)
            );
        }
        s += &row;
        s += "\n";
    };
    for d in &datasets {
        ours_row(format!("splatmark, {d}"), &|r: &PaperRun| r.dataset == *d);
    }
    if datasets.len() > 1 {
        ours_row("**splatmark, mean**".into(), &|_| true);
    }

    // Tables 2 and 3.
    let mut attack_table = |title: &str, cols: &[(&str, &str)], published: &[(&str, &[f64])]| {
        s += &format!("\n**{title} (32 bits, test views)**\n\n| method |");
        for (_, label) in cols {
            s += &format!(" {label} |");
        }
        s += "\n|---|";
        s += &"---|".repeat(cols.len());
        s += "\n";
        for (name, v) in published {
            s += &format!("| {name} |");
            for x in *v {
                s += &format!(" {x:.2} |");
            }
            s += "\n";
        }
        let mut ours = |label: String, pick: &dyn Fn(&PaperRun) -> bool| {
            s += &format!("| {label} |");
            for (row, _) in cols {
                let p = |r: &PaperRun| pick(r) && r.variant == "default" && r.bits == 32;
                s += &format!(" {} |", cell(runs, p, row, 2));
            }
            s += "\n";
        };
        for d in &datasets {
            ours(format!("splatmark, {d}"), &|r: &PaperRun| r.dataset == *d);
        }
        if datasets.len() > 1 {
            ours("**splatmark, mean**".into(), &|_| true);
        }
    };
    let t2: Vec<(&str, &[f64])> = PUBLISHED_T2.iter().map(|(n, v)| (*n, &v[..])).collect();
    attack_table("Table 2: image attacks", &IMAGE_COLS, &t2);
    let t3: Vec<(&str, &[f64])> = PUBLISHED_T3.iter().map(|(n, v)| (*n, &v[..])).collect();
    attack_table("Table 3: model attacks", &MODEL_COLS, &t3);

    if report.variants.is_empty() {
        return s;
    }
    // Table 5.
    let mark = |b: bool| if b { "✓" } else { "–" };
    s +=
        "\n**Table 5: ablation of the paper's recipe (32 bits, test views; published | ours)**\n\n";
    s += "| SBAG | group mask | decoupling | bit acc (paper) | bit acc (ours) | PSNR (paper) | PSNR (ours) | SSIM (paper) | SSIM (ours) |\n|---|---|---|---|---|---|---|---|---|\n";
    for (name, p) in PUBLISHED_T5 {
        let Some(v) = report.variants.iter().find(|v| v.name == name) else {
            continue;
        };
        let pick = |r: &PaperRun| r.variant == name;
        s += &format!(
            "| {} | {} | {} | {:.2} | {} | {:.2} | {} | {:.3} | {} |\n",
            mark(v.sbag),
            mark(v.group_mask),
            mark(v.decoupled),
            p[0],
            cell(runs, pick, "clean", 2),
            p[1],
            cell(runs, pick, "psnr", 2),
            p[2],
            cell(runs, pick, "ssim", 3)
        );
    }
    // Table 6.
    s += "\n**Table 6: carrier budget (32 bits, test views; published | ours)**\n\n";
    s += "| budget | bit acc (paper) | bit acc (ours) | PSNR (paper) | PSNR (ours) | SSIM (paper) | SSIM (ours) | storage (paper) | storage (ours) |\n|---|---|---|---|---|---|---|---|---|\n";
    for (name, p) in PUBLISHED_T6 {
        let Some(v) = report.variants.iter().find(|v| v.name == name) else {
            continue;
        };
        let pick = |r: &PaperRun| r.variant == name;
        s += &format!(
            "| {} | {:.2} | {} | {:.2} | {} | {:.3} | {} | {:.0} MB | {} MB |\n",
            v.budget,
            p[0],
            cell(runs, pick, "clean", 2),
            p[1],
            cell(runs, pick, "psnr", 2),
            p[2],
            cell(runs, pick, "ssim", 3),
            p[4],
            cell(runs, pick, "storage_mb", 1)
        );
    }
    s
}

#[cfg(test)]
pub(crate) mod tests {
    use super::super::*;
    use super::*;
    use crate::verify::eval::{Row, SceneEval};

    pub(crate) fn run(
        dataset: &str,
        variant: &str,
        bits: usize,
        seed: u64,
        clean: f64,
        psnr: f64,
    ) -> PaperRun {
        let r = |name: &str, acc: f64| Row {
            name: name.into(),
            kind: "image".into(),
            bit_accuracy: acc,
            bit_accuracy_combined: acc,
            p_value: 0.5,
            detected: false,
            detection_rate_per_view: 0.0,
            psnr_vs_original: None,
            psnr_on_asset_vs_original: None,
            draws: Vec::new(),
            view_accuracy: Vec::new(),
        };
        PaperRun {
            dataset: dataset.into(),
            variant: variant.into(),
            bits,
            seed,
            train_views: 10,
            test_views: 5,
            gaussians: 100,
            gaussians_marked: 110,
            storage_bytes: 2_500_000,
            width: 40,
            height: 30,
            embed_s: 1.0,
            eval_s: 1.0,
            eval: SceneEval {
                views: 5,
                psnr,
                ssim: 0.99,
                psnr_on_asset: None,
                fpr: 1e-6,
                rows: vec![
                    r("clean", clean),
                    r("jpeg", clean - 0.1),
                    r("remove_20", 0.5),
                ],
                per_view: Vec::new(),
                noise_position_scale: None,
            },
        }
    }

    pub(crate) fn report(runs: Vec<PaperRun>, seeds: Vec<u64>, ablations: bool) -> PaperReport {
        let mut options = PaperOptions::full("d".into(), "c".into());
        options.seeds = seeds;
        PaperReport {
            options,
            fits: Vec::new(),
            variants: if ablations {
                ablation_variants(0)
            } else {
                Vec::new()
            },
            runs,
            wall_s: 1.0,
        }
    }

    #[test]
    fn ours_sit_beside_the_published_rows_as_mean_and_spread_over_seeds() {
        let runs = vec![
            run("lego", "default", 32, 0, 0.90, 36.0),
            run("lego", "default", 32, 1, 0.80, 34.0),
            run("fern", "default", 32, 0, 1.00, 40.0),
            run("fern", "default", 32, 1, 1.00, 40.0),
        ];
        let md = markdown(&report(runs, vec![0, 1], false));
        assert!(
            md.contains("| paper (Ours) | 98.46 | 35.98 | 0.982 | 0.041 |"),
            "{md}"
        );
        assert!(md.contains("| 3D-GSW | 97.22 | 83.71 |"), "{md}");
        // lego: 85 ± 5 % at 35 ± 1 dB; 48 and 64 bits were not run.
        assert!(
            md.contains(
                "| splatmark, lego | 85.00 ± 5.00 | 35.00 ± 1.00 | 0.990 ± 0.000 | n/a | – |"
            ),
            "{md}"
        );
        // The mean over datasets pools every run.
        assert!(
            md.contains("| **splatmark, mean** | 92.50 ± 8.29 |"),
            "{md}"
        );
        // Table 2 takes the attack rows by name; an attack not run is a dash.
        assert!(
            md.contains(
                "| splatmark, fern | 100.00 ± 0.00 | – | – | – | – | – | 90.00 ± 0.00 | – |"
            ),
            "{md}"
        );
        assert!(md.contains("mean ± std over 2 seeds"));
        assert!(
            !md.contains("Table 5"),
            "no ablation table without ablation runs"
        );
    }

    #[test]
    fn the_ablation_tables_pair_each_published_switch_setting_with_its_run() {
        let runs = vec![
            run("lego", "paper_no_mask", 32, 0, 0.75, 30.0),
            run("lego", "paper_budget_1%", 32, 0, 0.70, 31.0),
        ];
        let md = markdown(&report(runs, vec![0], true));
        assert!(
            md.contains("| ✓ | – | ✓ | 97.10 | 75.00 | 33.70 | 30.00 | 0.972 | 0.990 |"),
            "{md}"
        );
        assert!(md.contains("| – | – | – | 94.70 | – |"), "{md}");
        assert!(
            md.contains("| 1% | 97.19 | 70.00 | 34.98 | 31.00 | 0.980 | 0.990 | 164 MB | 2.5 MB |"),
            "{md}"
        );
    }
}
