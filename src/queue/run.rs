//! One job's work, on a blocking thread: read the uploaded scene and cameras, run the embedding
//! pipeline, write the watermarked scene. No database access here: the worker publishes.

use std::io::Write;
use std::ops::ControlFlow;
use std::path::Path;

use super::spec::JobSpec;
use crate::decoder::registry::Pair;
use crate::embed::attribution::AttributionRecord;
use crate::embed::pipeline::{EmbedError, EmbedReport, Progress, embed, split_views};
use crate::scene::camera::{read_cameras_bytes, resize_all};
use crate::scene::orbit::orbit_cameras;
use crate::scene::{Camera, Limits, SceneError, read_scene_bytes, write_ply};

/// Why a job failed (kept in the job row).
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    #[error("the stored scene cannot be read: {0}")]
    Scene(SceneError),
    #[error("the stored cameras cannot be read: {0}")]
    Cameras(SceneError),
    #[error("no training views: {0}")]
    Views(String),
    #[error("embedding failed: {0}")]
    Embed(EmbedError),
    #[error("writing the watermarked scene failed: {0}")]
    Write(String),
    #[error("the decoder cannot be loaded: {0}")]
    Decoder(String),
}

/// What a successful job produced.
pub struct JobOutput {
    pub gaussians: u64,
    pub sh_degree: u8,
    pub records: Vec<AttributionRecord>,
    pub report: serde_json::Value,
    /// How a dispute reads the bits: the asset reference it subtracts (`embed.reference`), the
    /// matched head (`embed.projection.matched`) and the decoder's digest.
    pub readout: crate::store::Readout,
    pub train_views: usize,
    pub held_out_views: usize,
}

/// The training cameras of a job: the uploaded ones (resized when asked) or orbit views.
pub fn job_cameras(
    g: &crate::scene::Gaussians,
    cameras: Option<&Path>,
    spec: &JobSpec,
) -> Result<Vec<Camera>, JobError> {
    match cameras.filter(|_| spec.use_cameras) {
        Some(p) => {
            // An uploaded file: read from its bytes alone, never opening what it names.
            let bytes = std::fs::read(p)
                .map_err(|e| JobError::Cameras(crate::scene::SceneError::IoPlain(e)))?;
            let (_, cams) = read_cameras_bytes(&bytes, "cameras").map_err(JobError::Cameras)?;
            Ok(resize_all(cams, spec.width, spec.height))
        }
        None => orbit_cameras(g, &spec.orbit).map_err(|e| JobError::Views(e.to_string())),
    }
}

/// The embedding report as the service stores it (in plaintext) and shows it to the asset's
/// readers: everything but the embedded bits, which are the secret payload `message ⊕ mask`
/// (`store::keys`).
pub fn stored_report(report: &EmbedReport) -> serde_json::Result<serde_json::Value> {
    let mut v = serde_json::to_value(report)?;
    if let Some(o) = v.as_object_mut() {
        o.remove("message_hex");
    }
    Ok(v)
}

/// Runs the embedding of `scene_bytes` (format hint `format`) and writes the watermarked scene
/// as INRIA binary PLY to `out`. `progress` may stop the job by returning `Break`.
#[allow(clippy::too_many_arguments)]
pub fn execute(
    scene_bytes: &[u8],
    format: &str,
    cameras: Option<&Path>,
    spec: &JobSpec,
    message: &[bool],
    decoders: &Pair,
    limits: &Limits,
    out: &mut impl Write,
    progress: impl FnMut(Progress) -> ControlFlow<()>,
) -> Result<JobOutput, JobError> {
    let g = read_scene_bytes(scene_bytes, Some(format), limits).map_err(JobError::Scene)?;
    let cams = job_cameras(&g, cameras, spec)?;
    let (train, held) = split_views(&cams, spec.holdout_every);
    if train.is_empty() {
        return Err(JobError::Views(format!(
            "{} views, none left after holding out every {}-th",
            cams.len(),
            spec.holdout_every
        )));
    }
    let e = embed(&g, &train, message, decoders, &spec.embed, progress).map_err(JobError::Embed)?;
    write_ply(&e.scene, &mut *out).map_err(|e| JobError::Write(e.to_string()))?;
    out.flush().map_err(|e| JobError::Write(e.to_string()))?;
    let mut report = stored_report(&e.report).map_err(|e| JobError::Write(e.to_string()))?;
    if let Some(o) = report.as_object_mut() {
        // Where the views were rendered: `cpu`, or the GPU adapter.
        o.insert(
            "rasterizer".into(),
            spec.embed.finetune.rasterizer.describe().into(),
        );
    }
    Ok(JobOutput {
        gaussians: e.scene.len() as u64,
        sh_degree: e.scene.sh_degree,
        records: e.records,
        report,
        readout: crate::store::Readout {
            reference: e.report.reference_logits.clone(),
            head: e
                .report
                .view_projection
                .clone()
                .filter(|p| p.head.is_some()),
            decoder: Some(e.report.decoder.clone()),
        },
        train_views: train.len(),
        held_out_views: held.len(),
    })
}
