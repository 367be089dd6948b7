//! What a watermarking job runs: the request's options resolved against the server's defaults
//! at enqueue time and stored in full with the job, so the job row says exactly what ran.

use serde::{Deserialize, Serialize};

use crate::config::Config;
use crate::embed::pipeline::EmbedOptions;
use crate::scene::orbit::OrbitOptions;

/// Options a client may send with `POST /v1/assets/{id}/watermark` (all optional).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct JobOptions {
    /// Orbit views (used when the asset has no cameras, or when `use_cameras` is false):
    /// count, elevations, width, height, fov, up axis.
    pub orbit: Option<serde_json::Value>,
    /// Train through the uploaded cameras when there are some (default true).
    pub use_cameras: Option<bool>,
    /// Resolution of the renders when training through uploaded cameras (aspect kept when one
    /// side is given).
    pub width: Option<u32>,
    pub height: Option<u32>,
    /// Every N-th view is held out of training (0: none).
    pub holdout_every: Option<usize>,
    /// Finetuning steps.
    pub steps: Option<usize>,
    /// The full embedding options (partial objects keep the defaults), as `splatmark embed
    /// --config` reads them.
    pub embed: Option<serde_json::Value>,
}

/// A fully resolved job.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobSpec {
    pub orbit: OrbitOptions,
    pub use_cameras: bool,
    pub width: Option<u32>,
    pub height: Option<u32>,
    pub holdout_every: usize,
    pub embed: EmbedOptions,
}

/// Largest render side a job may ask for.
pub const MAX_SIDE: u32 = 4096;
/// Most finetuning steps a job may ask for.
pub const MAX_STEPS: usize = 100_000;
/// Most views a job may ask for.
pub const MAX_VIEWS: usize = 1000;

impl JobOptions {
    /// Resolves against `cfg` for a `bits`-bit payload (the orbit's default view count depends
    /// on it: [`crate::config::ViewDefaults::orbit_for`]); the error says which option is wrong.
    pub fn resolve(&self, cfg: &Config, bits: usize) -> Result<JobSpec, String> {
        let mut embed: EmbedOptions = match &self.embed {
            Some(v) => {
                serde_json::from_value(v.clone()).map_err(|e| format!("options.embed: {e}"))?
            }
            None => EmbedOptions::default(),
        };
        if self.embed.is_none() {
            embed.finetune.steps = cfg.steps;
        }
        if let Some(s) = self.steps {
            embed.finetune.steps = s;
        }
        if !(1..=MAX_STEPS).contains(&embed.finetune.steps) {
            return Err(format!("options.steps must be 1 to {MAX_STEPS}"));
        }
        if embed.finetune.most_steps() > MAX_STEPS {
            // A job's worker time is bounded by what it may run, the stretched schedule
            // included, not by what it asked for.
            return Err(format!(
                "options.embed.finetune: steps (twice them when stretch_bce > 0, the default) \
                 + extra_steps must be at most {MAX_STEPS}, got {}",
                embed.finetune.most_steps()
            ));
        }
        crate::embed::pipeline::check_view_scales(&embed.view_scales)
            .map_err(|e| format!("options.embed.{e}"))?;
        embed
            .check_coarse()
            .map_err(|e| format!("options.embed.{e}"))?;
        if embed.view_scales.len() > 4 {
            return Err("options.embed.view_scales: at most 4 factors".into());
        }
        embed
            .finetune
            .validate()
            .map_err(|e| format!("options.embed.finetune: {e}"))?;
        let pr = &embed.projection;
        if pr.rank > 0 && !pr.matched {
            // The service's keys and /v1/verify carry the asset reference and a matched head,
            // not a rank-k projection: a job written through one would not verify (the CLI and
            // the bench decode through it).
            return Err(
                "options.embed.projection.rank: the rank-k view projection is a CLI and bench \
                 option; the service verifies through a matched head (projection.matched) only"
                    .into(),
            );
        }
        if pr.matched
            && !(pr.lambda.is_finite()
                && (1e-6..=1e3).contains(&pr.lambda)
                && pr.views <= 1000
                && pr.nuisance <= 1000
                && pr.max_angle_deg.is_finite()
                && pr.zoom.is_finite())
        {
            return Err(
                "options.embed.projection: lambda must be in [1e-6, 1000], views and nuisance \
                 at most 1000, angles and zoom finite"
                    .into(),
            );
        }
        if embed.extra_views > 1000 {
            return Err("options.embed.extra_views: at most 1000".into());
        }
        embed
            .path
            .validate()
            .map_err(|e| format!("options.embed.{e}"))?;
        if embed.finetune.check_every == 0 {
            return Err("options.embed.finetune.check_every must be at least 1".into());
        }
        let mut orbit = OrbitOptions {
            count: cfg.views.orbit_for(bits),
            width: cfg.views.width,
            height: cfg.views.height,
            ..OrbitOptions::default()
        };
        if let Some(v) = &self.orbit {
            // Fields the client names override the server's defaults.
            let mut base = serde_json::to_value(&orbit).map_err(|e| e.to_string())?;
            let (Some(b), Some(o)) = (base.as_object_mut(), v.as_object()) else {
                return Err("options.orbit must be an object".into());
            };
            for (k, x) in o {
                b.insert(k.clone(), x.clone());
            }
            orbit = serde_json::from_value(base).map_err(|e| format!("options.orbit: {e}"))?;
        }
        orbit
            .validate()
            .map_err(|e| format!("options.orbit: {e}"))?;
        if orbit.count > MAX_VIEWS || orbit.width > MAX_SIDE || orbit.height > MAX_SIDE {
            return Err(format!(
                "options.orbit: at most {MAX_VIEWS} views of at most {MAX_SIDE} px a side"
            ));
        }
        for (name, side) in [("width", self.width), ("height", self.height)] {
            if let Some(s) = side
                && !(16..=MAX_SIDE).contains(&s)
            {
                return Err(format!("options.{name} must be 16 to {MAX_SIDE}"));
            }
        }
        Ok(JobSpec {
            orbit,
            use_cameras: self.use_cameras.unwrap_or(true),
            width: self.width,
            height: self.height,
            holdout_every: self.holdout_every.unwrap_or(8),
            embed,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn defaults_come_from_the_server_config() {
        let cfg = Config::default();
        let s = JobOptions::default().resolve(&cfg, 32).unwrap();
        assert_eq!(s.orbit.count, cfg.views.orbit);
        assert_eq!(s.orbit.width, cfg.views.width);
        assert_eq!(s.embed.finetune.steps, cfg.steps);
        assert!(s.use_cameras);
        assert_eq!(s.holdout_every, 8);
        // Longer payloads train on `orbit_long` views, unless the client names a count.
        let cfg = Config {
            views: crate::config::ViewDefaults {
                orbit: 24,
                ..cfg.views.clone()
            },
            ..cfg
        };
        assert_eq!(
            JobOptions::default().resolve(&cfg, 32).unwrap().orbit.count,
            24
        );
        for bits in [48, 64] {
            let s = JobOptions::default().resolve(&cfg, bits).unwrap();
            assert_eq!(s.orbit.count, cfg.views.orbit_long);
        }
        let named: JobOptions = serde_json::from_value(json!({"orbit": {"count": 12}})).unwrap();
        assert_eq!(named.resolve(&cfg, 64).unwrap().orbit.count, 12);
    }

    #[test]
    fn named_fields_override_and_the_rest_stay() {
        let o: JobOptions = serde_json::from_value(json!({
            "orbit": {"count": 6, "width": 64},
            "steps": 7,
            "embed": {"no_group_mask": true}
        }))
        .unwrap();
        let s = o.resolve(&Config::default(), 32).unwrap();
        assert_eq!(s.orbit.count, 6);
        assert_eq!(s.orbit.width, 64);
        assert_eq!(s.orbit.height, Config::default().views.height);
        assert_eq!(s.embed.finetune.steps, 7);
        assert!(s.embed.no_group_mask);
        // The spec survives the job row.
        let back: JobSpec = serde_json::from_value(serde_json::to_value(&s).unwrap()).unwrap();
        assert_eq!(back, s);
    }

    #[test]
    fn bad_options_are_named() {
        let cfg = Config::default();
        for (v, needle) in [
            (json!({"steps": 0}), "steps"),
            (json!({"orbit": {"count": 0}}), "orbit"),
            (json!({"orbit": {"colour": 1}}), "orbit"),
            (json!({"width": 100000}), "width"),
            (json!({"embed": {"finetune": {"steps": "many"}}}), "embed"),
            (
                json!({"steps": 10, "embed": {"finetune": {"extra_steps": MAX_STEPS}}}),
                "extra_steps",
            ),
            // The stretched schedule counts: 60 001 steps may run 120 002.
            (json!({"steps": MAX_STEPS / 2 + 1}), "stretch_bce"),
            (
                json!({"embed": {"finetune": {"check_every": 0}}}),
                "check_every",
            ),
            (json!({"embed": {"view_scales": [1.0, 9.0]}}), "view_scales"),
            (json!({"embed": {"view_scales": []}}), "view_scales"),
            (
                json!({"embed": {"coarse_margin_db": -2.0}}),
                "coarse_margin_db",
            ),
            (
                json!({"embed": {"coarse_wm_lr_factor": 0.0}}),
                "coarse_wm_lr_factor",
            ),
            (
                json!({"embed": {"coarse_bound_drop_db": 38.0}}),
                "coarse_bound_drop_db",
            ),
            (
                json!({"embed": {"projection": {"rank": 16, "matched": false}}}),
                "projection.rank",
            ),
            (
                json!({"embed": {"projection": {"lambda": -1.0}}}),
                "projection",
            ),
            (
                json!({"embed": {"finetune": {"wm_sharpness": 0.0}}}),
                "wm_sharpness",
            ),
            (
                json!({"embed": {"finetune": {"stretch_bce": -0.5}}}),
                "stretch_bce",
            ),
            (
                json!({"embed": {"finetune": {"wm_geometry": true}}}),
                "wm_geometry",
            ),
            (
                json!({"embed": {"finetune": {"wm_lr_scale": 0.0}}}),
                "wm_lr_scale",
            ),
            (
                json!({"embed": {"finetune": {"target_psnr": -38.0}}}),
                "target_psnr",
            ),
            (
                json!({"embed": {"finetune": {"weights": {"vis": -1.0}}}}),
                "weights.vis",
            ),
            (
                json!({"embed": {"finetune": {"lr": {"dc": 1e39}}}}),
                "lr.dc",
            ),
            // The coarse run's rate is the main run's times the factor: refused before the job
            // runs, not at the switch.
            (
                json!({"embed": {"finetune": {"wm_lr_scale": 900.0}}}),
                "coarse run's wm_lr_scale",
            ),
            (json!({"embed": {"path": {"per_gap": 100}}}), "path.per_gap"),
            (
                json!({"embed": {"path": {"max_turn_deg": 0.0}}}),
                "path.max_turn_deg",
            ),
        ] {
            let o: JobOptions = serde_json::from_value(v).unwrap();
            let e = o.resolve(&cfg, 32).unwrap_err();
            assert!(e.contains(needle), "{e}");
        }
        assert!(serde_json::from_value::<JobOptions>(json!({"stepz": 3})).is_err());
        // The stretch counts only when it is on.
        let resolve = |v| {
            serde_json::from_value::<JobOptions>(v)
                .unwrap()
                .resolve(&cfg, 32)
        };
        assert!(resolve(json!({"steps": MAX_STEPS / 2})).is_ok());
        let fixed = json!({"steps": MAX_STEPS, "embed": {"finetune": {"stretch_bce": 0.0}}});
        assert!(resolve(fixed).is_ok());
    }

    #[test]
    fn a_spec_survives_the_job_row_exactly() {
        // Job rows hold the spec as JSON text; idempotent replays compare it with a fresh one,
        // so floats must print and parse back bit-exactly (serde_json's float_roundtrip).
        let s = JobOptions::default()
            .resolve(&Config::default(), 32)
            .unwrap();
        let v = serde_json::to_value(&s).unwrap();
        let back: serde_json::Value =
            serde_json::from_str(&serde_json::to_string(&v).unwrap()).unwrap();
        assert_eq!(back, v);
    }
}
