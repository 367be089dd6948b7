//! Checkpoints: the `<out>.ckpt/step-NNNNNNNN/` folders (written atomically, pruned, listed and
//! read back; shared with the optimiser-as-encoder trainer) and what this trainer stores in them.

use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::optim::{AdamConfig, ModuleOptimizer};
use burn::tensor::Bytes;
use serde::{Deserialize, Serialize};

use super::{LogEntry, StartedFrom, TrainConfig, TrainError, io_err};
use crate::decoder::artifact;

/// What a checkpoint's `state.json` holds.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CheckpointState {
    /// Format version (1).
    pub version: u32,
    /// Steps done.
    pub step: usize,
    /// The run's configuration.
    pub config: TrainConfig,
    /// The RNG state: step `k` draws from `step_seed(config.seed, k)`.
    pub rng: String,
    /// Training wall time so far, summed over resumed sessions (seconds).
    pub wall_s: f64,
    /// Progress lines so far.
    pub history: Vec<LogEntry>,
    /// The artifact the run started from (`--init`).
    #[serde(default)]
    pub started_from: Option<StartedFrom>,
}

pub(super) fn optimizer() -> ModuleOptimizer {
    AdamConfig::new().init()
}

pub(super) fn record_err(path: &Path, e: impl std::fmt::Display) -> TrainError {
    TrainError::Record {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// A module's weights as burnpack bytes.
pub(super) fn module_bytes<M: Module>(
    module: M,
    path_for_errors: &Path,
) -> Result<Vec<u8>, TrainError> {
    artifact::to_burnpack(module).map_err(|e| record_err(path_for_errors, e))
}

/// Loads burnpack bytes into `module`.
pub(super) fn load_module_bytes<M: Module>(
    module: M,
    bytes: Vec<u8>,
    path: &Path,
) -> Result<M, TrainError> {
    artifact::from_burnpack(module, bytes).map_err(|e| record_err(path, e))
}

/// The checkpoint folder of an output path: `<out>.ckpt`.
pub fn checkpoint_root(out: &Path) -> PathBuf {
    let mut s = out.as_os_str().to_owned();
    s.push(".ckpt");
    PathBuf::from(s)
}

/// Complete checkpoints under `root`, oldest first: `(step, folder)`.
pub fn list_checkpoints(root: &Path) -> Vec<(usize, PathBuf)> {
    let mut out: Vec<(usize, PathBuf)> = std::fs::read_dir(root)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let step = name.strip_prefix("step-")?.parse().ok()?;
            let path = e.path();
            path.join("state.json").is_file().then_some((step, path))
        })
        .collect();
    out.sort();
    out
}

/// Reads the checkpoint folder `dir` written by [`write_checkpoint`]: its `state.json` as `S`,
/// the weights' burnpack bytes (`net.bpk`) and the Adam state (`optim.bpk`). Shared by both
/// trainers.
pub fn read_checkpoint<S: serde::de::DeserializeOwned>(
    dir: &Path,
) -> Result<(S, Vec<u8>, ModuleOptimizer), TrainError> {
    let state_path = dir.join("state.json");
    let text = std::fs::read(&state_path).map_err(io_err(&state_path))?;
    let state: S = serde_json::from_slice(&text).map_err(|source| TrainError::Json {
        path: state_path.clone(),
        source,
    })?;
    let net_path = dir.join("net.bpk");
    let net = std::fs::read(&net_path).map_err(io_err(&net_path))?;
    let optim_path = dir.join("optim.bpk");
    let bytes = std::fs::read(&optim_path).map_err(io_err(&optim_path))?;
    let optim = optimizer()
        .from_bytes(Bytes::from_bytes_vec(bytes))
        .map_err(|e| record_err(&optim_path, e))?;
    Ok((state, net, optim))
}

/// Writes `files` as the checkpoint `root/step-NNNNNNNN` atomically (a temporary folder,
/// every file synced, then renamed; a crash leaves whole checkpoints only) and keeps the newest
/// `keep` checkpoints. Shared by both trainers.
pub fn write_checkpoint(
    root: &Path,
    step: usize,
    files: &[(&str, &[u8])],
    keep: usize,
) -> Result<PathBuf, TrainError> {
    std::fs::create_dir_all(root).map_err(io_err(root))?;
    let final_dir = root.join(format!("step-{step:08}"));
    let tmp = tempfile::Builder::new()
        .prefix(".tmp-step-")
        .tempdir_in(root)
        .map_err(io_err(root))?;
    for (name, bytes) in files {
        let p = tmp.path().join(name);
        std::fs::write(&p, bytes).map_err(io_err(&p))?;
        std::fs::File::open(&p)
            .and_then(|f| f.sync_all())
            .map_err(io_err(&p))?;
    }
    if final_dir.exists() {
        std::fs::remove_dir_all(&final_dir).map_err(io_err(&final_dir))?;
    }
    let tmp_path = tmp.keep();
    std::fs::rename(&tmp_path, &final_dir).map_err(io_err(&final_dir))?;
    let all = list_checkpoints(root);
    for (_, old) in all.iter().take(all.len().saturating_sub(keep.max(1))) {
        let _ = std::fs::remove_dir_all(old);
    }
    Ok(final_dir)
}
