//! Progress of the long commands on stderr (`--progress auto|bar|lines|json|none`): a bar with
//! phase, step, rate and ETA on a terminal; the plain progress lines for logs; one JSON object
//! per line for programs; or nothing. `auto` draws the bar when stderr is a terminal and stays
//! quiet otherwise.

use std::io::IsTerminal;
use std::time::{Duration, Instant};

use clap::ValueEnum;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// How a command reports its progress.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, ValueEnum)]
pub(crate) enum ProgressMode {
    /// A bar on a terminal, nothing otherwise.
    #[default]
    Auto,
    /// A bar (drawn only where stderr is a terminal).
    Bar,
    /// Plain text lines, for logs.
    Lines,
    /// One JSON object per line: `{"phase", "step", "total", "rate", "eta_s", "elapsed_s", "message"}`.
    Json,
    /// Nothing.
    None,
}

/// A command's progress reporter.
pub(crate) struct Progress {
    mode: ProgressMode,
    bar: Option<ProgressBar>,
    phase: String,
    total: u64,
    started: Instant,
    last_json: Option<Instant>,
}

/// Least time between two JSON progress lines of one phase (its first and last step always
/// print).
const JSON_EVERY: Duration = Duration::from_secs(1);

impl Progress {
    pub(crate) fn new(mode: ProgressMode) -> Self {
        let mode = match mode {
            ProgressMode::Auto if std::io::stderr().is_terminal() => ProgressMode::Bar,
            ProgressMode::Auto => ProgressMode::None,
            m => m,
        };
        Self {
            mode,
            bar: None,
            phase: String::new(),
            total: 0,
            started: Instant::now(),
            last_json: None,
        }
    }

    /// Whether plain lines are wanted (the commands' own per-step text).
    pub(crate) fn lines(&self) -> bool {
        self.mode == ProgressMode::Lines
    }

    /// A new phase of `total` steps (0: a phase without steps, shown as a spinner).
    pub(crate) fn phase(&mut self, name: &str, total: u64) {
        self.finish_bar();
        self.phase = name.to_string();
        self.total = total;
        self.started = Instant::now();
        self.last_json = None;
        match self.mode {
            ProgressMode::Bar => {
                let bar = if total > 0 {
                    let b =
                        ProgressBar::with_draw_target(Some(total), ProgressDrawTarget::stderr());
                    b.set_style(
                        ProgressStyle::with_template(
                            "{prefix:>10} [{bar:30}] {pos}/{len} {per_sec} ETA {eta} {wide_msg}",
                        )
                        .expect("a valid template")
                        .progress_chars("=> "),
                    );
                    b
                } else {
                    let b = ProgressBar::with_draw_target(None, ProgressDrawTarget::stderr());
                    b.set_style(
                        ProgressStyle::with_template("{prefix:>10} {spinner} {elapsed} {wide_msg}")
                            .expect("a valid template"),
                    );
                    b.enable_steady_tick(Duration::from_millis(200));
                    b
                };
                bar.set_prefix(name.to_string());
                self.bar = Some(bar);
            }
            ProgressMode::Lines => eprintln!("{name}…"),
            ProgressMode::Json => self.json(0, ""),
            _ => {}
        }
    }

    /// Step `step` (1-based) of the phase is done; `message` describes it.
    pub(crate) fn step(&mut self, step: u64, message: &str) {
        match self.mode {
            ProgressMode::Bar => {
                if let Some(b) = &self.bar {
                    b.set_position(step);
                    b.set_message(message.to_string());
                }
            }
            ProgressMode::Json => {
                let due = self.last_json.is_none_or(|t| t.elapsed() >= JSON_EVERY);
                if due || step == 1 || step == self.total {
                    self.json(step, message);
                }
            }
            _ => {}
        }
    }

    /// A line of text that is not progress (kept above the bar; a `{"message"}` in JSON).
    pub(crate) fn println(&self, text: &str) {
        match self.mode {
            ProgressMode::Bar => match &self.bar {
                Some(b) => b.println(text),
                None => eprintln!("{text}"),
            },
            ProgressMode::Lines => eprintln!("{text}"),
            ProgressMode::Json => {
                eprintln!(
                    "{}",
                    serde_json::json!({ "phase": self.phase, "message": text })
                )
            }
            _ => {}
        }
    }

    /// Ends the last phase.
    pub(crate) fn finish(&mut self) {
        self.finish_bar();
    }

    fn finish_bar(&mut self) {
        if let Some(b) = self.bar.take() {
            b.finish_and_clear();
        }
    }

    fn json(&mut self, step: u64, message: &str) {
        let elapsed = self.started.elapsed().as_secs_f64();
        let rate = if elapsed > 0.0 {
            step as f64 / elapsed
        } else {
            0.0
        };
        let eta = (rate > 0.0 && self.total >= step).then(|| (self.total - step) as f64 / rate);
        eprintln!(
            "{}",
            serde_json::json!({
                "phase": self.phase,
                "step": step,
                "total": self.total,
                "rate": rate,
                "eta_s": eta,
                "elapsed_s": elapsed,
                "message": message,
            })
        );
        self.last_json = Some(Instant::now());
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        self.finish_bar();
    }
}
