//! Fitted scenes as reproducible artifacts: a fit is stored in a cache folder under a key made
//! of the dataset's fingerprint (camera files, every image's bytes, the image options) and the
//! whole [`FitConfig`], so the same command on the same data reuses it and anything else fits
//! afresh. An interrupted fit resumes from its checkpoint in the same folder.

use super::{DataOptions, Dataset, FitConfig, FitError, Fitter, Quality, checkpoint};
use crate::scene::{Gaussians, Limits, read_scene, write_ply};
use sha2::{Digest, Sha256};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Bumped when a change of the fitting code changes what a configuration produces.
const CACHE_VERSION: u32 = 1;

/// What a cached fit records beside its scene.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FitRecord {
    pub name: String,
    pub key: String,
    pub config: FitConfig,
    pub width: u32,
    pub height: u32,
    pub train_views: usize,
    pub test_views: usize,
    pub gaussians: usize,
    /// The scene on the dataset's test views (the training views when it has none).
    pub test: Quality,
    /// Seconds of optimisation (summed over resumed parts).
    pub seconds: f64,
    /// Reused from the cache by this run (not stored).
    #[serde(skip)]
    pub cached: bool,
}

/// A fitted scene with the dataset it was fitted to.
pub struct Fitted {
    pub dataset: Dataset,
    pub scene: Gaussians,
    pub record: FitRecord,
}

/// The cache key of fitting `ds` with `cfg`.
pub fn key(ds: &Dataset, cfg: &FitConfig) -> String {
    let mut h = Sha256::new();
    h.update(CACHE_VERSION.to_le_bytes());
    h.update(ds.fingerprint.as_bytes());
    h.update(serde_json::to_vec(cfg).expect("a config serialises"));
    hex::encode(&h.finalize()[..8])
}

/// The fit of the dataset in `dir` under `cfg`, from `cache` when it is there, else fitted (and
/// stored); `log` gets progress lines.
pub fn fitted(
    name: &str,
    dir: &Path,
    data: &DataOptions,
    cfg: &FitConfig,
    cache: &Path,
    log: &mut dyn FnMut(&str),
) -> Result<Fitted, FitError> {
    cfg.validate()?;
    let ds = Dataset::open(dir, data)?;
    let key = key(&ds, cfg);
    std::fs::create_dir_all(cache).map_err(|e| FitError::io(cache, e))?;
    let base = cache.join(format!("{name}-{key}"));
    let with = |ext: &str| PathBuf::from(format!("{}.{ext}", base.display()));
    let (ply, json, ckpt) = (with("ply"), with("json"), with("fit-ckpt"));
    if ply.is_file() && json.is_file() {
        let rec: Option<FitRecord> = std::fs::read(&json)
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok());
        let scene = read_scene(&ply, &Limits::default()).ok();
        if let (Some(mut record), Some(scene)) = (rec, scene)
            && record.key == key
            && record.gaussians == scene.len()
        {
            record.cached = true;
            log(&format!(
                "{name}: reusing the fit {} ({} Gaussians, test PSNR {:.2} dB)",
                ply.display(),
                scene.len(),
                record.test.psnr
            ));
            return Ok(Fitted {
                dataset: ds,
                scene,
                record,
            });
        }
        log(&format!(
            "{name}: the cached fit {} is unreadable; fitting again",
            ply.display()
        ));
    }
    let (mut f, mut seconds) = match checkpoint::load(&ckpt, &ds) {
        Ok(f) if &f.cfg == cfg => {
            log(&format!("{name}: resuming the fit at step {}", f.step));
            let spent = std::fs::read(with("seconds"))
                .ok()
                .and_then(|b| String::from_utf8(b).ok())
                .and_then(|s| s.trim().parse::<f64>().ok())
                .unwrap_or(0.0);
            (f, spent)
        }
        _ => (Fitter::new(&ds, cfg.clone())?, 0.0),
    };
    let (w, h) = ds.size();
    log(&format!(
        "{name}: fitting {} steps on {} views at {w}×{h} (cache key {key})…",
        cfg.iterations,
        ds.train.len()
    ));
    let t0 = Instant::now();
    let every = (cfg.iterations / 10).max(1);
    while f.step < cfg.iterations {
        let r = f.step(&ds)?;
        if f.step % every == 0 || f.step == cfg.iterations {
            log(&format!(
                "  step {}/{}: train PSNR {:.2} dB, {} Gaussians, {:.0} s",
                f.step,
                cfg.iterations,
                r.psnr,
                r.gaussians,
                seconds + t0.elapsed().as_secs_f64()
            ));
            if f.step < cfg.iterations {
                checkpoint::save(&f, &ckpt)?;
                let s = format!("{}", seconds + t0.elapsed().as_secs_f64());
                std::fs::write(with("seconds"), s).map_err(|e| FitError::io(&base, e))?;
            }
        }
    }
    seconds += t0.elapsed().as_secs_f64();
    let scene = f.output();
    let views = if ds.test.is_empty() {
        &ds.train
    } else {
        &ds.test
    };
    let test = f.evaluate(&ds, views)?;
    let record = FitRecord {
        name: name.to_string(),
        key,
        config: cfg.clone(),
        width: w,
        height: h,
        train_views: ds.train.len(),
        test_views: ds.test.len(),
        gaussians: scene.len(),
        test,
        seconds,
        cached: false,
    };
    write_atomic(&ply, |w| {
        write_ply(&scene, w).map_err(std::io::Error::other)
    })?;
    let rec_json = serde_json::to_vec_pretty(&record).expect("a record serialises");
    write_atomic(&json, |w| w.write_all(&rec_json))?;
    for done in [ckpt, with("seconds")] {
        let _ = std::fs::remove_file(done);
    }
    log(&format!(
        "{name}: fitted in {seconds:.0} s: {} Gaussians, test PSNR {:.2} dB → {}",
        scene.len(),
        record.test.psnr,
        ply.display()
    ));
    Ok(Fitted {
        dataset: ds,
        scene,
        record,
    })
}

/// Writes `path` through a temporary file in its folder, synced and renamed into place.
pub(crate) fn write_atomic(
    path: &Path,
    f: impl FnOnce(&mut std::io::BufWriter<&mut std::fs::File>) -> std::io::Result<()>,
) -> Result<(), FitError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let io = |e| FitError::io(path, e);
    let mut tmp = tempfile::NamedTempFile::new_in(dir).map_err(io)?;
    {
        let mut w = std::io::BufWriter::new(tmp.as_file_mut());
        f(&mut w).map_err(io)?;
        w.flush().map_err(io)?;
    }
    tmp.as_file().sync_all().map_err(io)?;
    tmp.persist(path).map_err(|e| io(e.error))?;
    Ok(())
}
