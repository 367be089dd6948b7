//! The `splatmark` command line.

use crate::render::{RenderOptions, render, to_rgb8};
use crate::scene::bounds::{full_bounds, robust_bounds};
use crate::scene::camera::read_cameras;
use crate::scene::format::read_scene_bytes_detect;
use crate::scene::orbit::{OrbitOptions, UpAxis, orbit_cameras};
use crate::scene::{Camera, Gaussians, Limits, write_ply};
use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(Parser, Debug)]
#[command(
    name = "splatmark",
    version,
    about = "Watermarking for 3D Gaussian Splatting assets"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Print what a scene file holds, as JSON: format, count, SH degree, bounds.
    Info {
        /// Scene file (.ply, compressed .ply, .splat, .spz).
        scene: PathBuf,
        #[command(flatten)]
        limits: LimitArgs,
    },
    /// Render a scene through its cameras or orbit views to PNG files.
    Render(RenderArgs),
    /// Convert any supported scene file to an INRIA binary PLY (opens in INRIA's viewer,
    /// SuperSplat and Spark).
    Convert {
        /// Scene file (.ply, compressed .ply, .splat, .spz).
        scene: PathBuf,
        /// Output .ply file (written atomically: a temporary file renamed into place).
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        limits: LimitArgs,
    },
}

#[derive(Args, Debug)]
struct LimitArgs {
    /// Refuse scenes with more Gaussians than this.
    #[arg(long, default_value_t = Limits::default().max_gaussians)]
    max_gaussians: usize,
}

#[derive(Args, Debug)]
struct RenderArgs {
    /// Scene file (.ply, compressed .ply, .splat, .spz).
    scene: PathBuf,
    /// Camera file: INRIA cameras.json, NeRF transforms.json or LLFF poses_bounds.npy.
    #[arg(long, conflicts_with = "orbit")]
    cameras: Option<PathBuf>,
    /// Render N orbit views around the scene's robust bounds instead (default when no
    /// --cameras is given: 24).
    #[arg(long)]
    orbit: Option<usize>,
    /// Image width (orbit default 800; with --cameras the camera's own width, intrinsics scaled).
    #[arg(long)]
    width: Option<u32>,
    /// Image height (orbit default 800; with --cameras the camera's own height).
    #[arg(long)]
    height: Option<u32>,
    /// Orbit: the scene's up axis (+x, -x, +y, -y, +z, -z).
    #[arg(long, default_value = "-y")]
    up: UpAxis,
    /// Orbit: elevations in degrees, comma separated.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    elevations: Option<Vec<f32>>,
    /// Orbit: vertical field of view in degrees.
    #[arg(long, default_value_t = 45.0)]
    fov: f32,
    /// Background colour r,g,b in [0, 1].
    #[arg(long, value_delimiter = ',', num_args = 3, default_values_t = [0.0, 0.0, 0.0])]
    background: Vec<f32>,
    /// Use at most this SH degree.
    #[arg(long)]
    sh_degree: Option<u8>,
    /// Render only the first N cameras.
    #[arg(long)]
    limit: Option<usize>,
    /// Output folder (created if missing).
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    limits: LimitArgs,
}

/// Runs the command line; errors are printed to stderr with their causes.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Info { scene, limits } => info(&scene, &limits),
        Command::Render(args) => render_cmd(&args),
        Command::Convert { scene, out, limits } => convert(&scene, &out, &limits),
    }
}

fn convert(path: &Path, out: &Path, limits: &LimitArgs) -> Result<()> {
    let (format, g) = load(path, limits)?;
    let dir = out
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let mut tmp = tempfile::NamedTempFile::new_in(dir)
        .with_context(|| format!("cannot create a file in {}", dir.display()))?;
    write_ply(&g, std::io::BufWriter::new(tmp.as_file_mut()))?;
    tmp.as_file().sync_all()?;
    tmp.persist(out)
        .with_context(|| format!("cannot write {}", out.display()))?;
    eprintln!(
        "{} ({format}, {} Gaussians, SH {}) → {}",
        path.display(),
        g.len(),
        g.sh_degree,
        out.display()
    );
    Ok(())
}

fn load(path: &Path, limits: &LimitArgs) -> Result<(crate::scene::Format, Gaussians)> {
    let limits = Limits {
        max_gaussians: limits.max_gaussians,
        ..Limits::default()
    };
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    let ext = path.extension().and_then(|e| e.to_str());
    read_scene_bytes_detect(&bytes, ext, &limits)
        .with_context(|| format!("cannot load scene {}", path.display()))
}

fn info(path: &Path, limits: &LimitArgs) -> Result<()> {
    let (format, g) = load(path, limits)?;
    let json = serde_json::json!({
        "path": path,
        "format": format,
        "count": g.len(),
        "sh_degree": g.sh_degree,
        "bounds": full_bounds(&g),
        "robust_bounds_2pct": robust_bounds(&g, 0.02),
        "file_bytes": std::fs::metadata(path).map(|m| m.len()).ok(),
    });
    println!("{}", serde_json::to_string_pretty(&json)?);
    Ok(())
}

fn render_cmd(a: &RenderArgs) -> Result<()> {
    let (_, g) = load(&a.scene, &a.limits)?;
    let mut cams: Vec<Camera> = match &a.cameras {
        Some(path) => {
            let cams = read_cameras(path)
                .with_context(|| format!("cannot load cameras {}", path.display()))?;
            match (a.width, a.height) {
                (None, None) => cams,
                (w, h) => cams
                    .into_iter()
                    .map(|c| {
                        let w = w.unwrap_or_else(|| {
                            let h = h.unwrap_or(c.height);
                            (c.width as f64 * h as f64 / c.height as f64).round() as u32
                        });
                        let h = h.unwrap_or_else(|| {
                            (c.height as f64 * w as f64 / c.width as f64).round() as u32
                        });
                        c.resized(w.max(1), h.max(1))
                    })
                    .collect(),
            }
        }
        None => {
            let mut o = OrbitOptions {
                count: a.orbit.unwrap_or(24),
                width: a.width.unwrap_or(800),
                height: a.height.unwrap_or(800),
                fov_y_deg: a.fov,
                up: a.up,
                ..OrbitOptions::default()
            };
            if let Some(e) = &a.elevations {
                o.elevations_deg = e.clone();
            }
            orbit_cameras(&g, &o)?
        }
    };
    if let Some(n) = a.limit {
        cams.truncate(n);
    }
    if cams.is_empty() {
        bail!("no cameras to render");
    }
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create {}", a.out.display()))?;
    let opts = RenderOptions {
        background: [a.background[0], a.background[1], a.background[2]],
        sh_degree: a.sh_degree,
        ..RenderOptions::default()
    };
    for (k, cam) in cams.iter().enumerate() {
        let t = std::time::Instant::now();
        let r = render(&g, cam, &opts).with_context(|| format!("rendering {}", cam.name))?;
        let file = a.out.join(format!("{:03}_{}.png", k, safe_name(&cam.name)));
        to_rgb8(r.width, r.height, &r.image)
            .save(&file)
            .with_context(|| format!("cannot write {}", file.display()))?;
        eprintln!(
            "{} ({}×{}, {} visible) in {:.0} ms",
            file.display(),
            r.width,
            r.height,
            r.stats.visible,
            t.elapsed().as_secs_f64() * 1e3
        );
    }
    Ok(())
}

/// A camera name reduced to characters that are safe in a file name.
fn safe_name(name: &str) -> String {
    let s: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .take(64)
        .collect();
    if s.is_empty() { "view".into() } else { s }
}
