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
    /// Steps already done when the phase started (its rate counts the steps since).
    first: u64,
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
            first: 0,
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
        self.phase_from(name, total, 0);
    }

    /// A new phase of `total` steps of which `first` are already done (an embedding that
    /// switched decoders counts on from the steps it discarded; its rate and ETA read the
    /// steps since).
    pub(crate) fn phase_from(&mut self, name: &str, total: u64, first: u64) {
        self.finish_bar();
        self.phase = name.to_string();
        self.total = total;
        self.first = first.min(total);
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
                if self.first > 0 {
                    bar.set_position(self.first);
                    bar.reset_eta();
                }
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
                if due || step == self.first + 1 || step == self.total {
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

    /// A log line a command has always printed (a training's settings, its periodic lines,
    /// checkpoints): above the bar, as a `{"message"}` in JSON, and plain on stderr otherwise —
    /// also when progress is off, so logs of background runs keep them.
    pub(crate) fn log_line(&self, text: &str) {
        match self.mode {
            ProgressMode::Bar | ProgressMode::Json => self.println(text),
            _ => eprintln!("{text}"),
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
            step.saturating_sub(self.first) as f64 / elapsed
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

/// The benches' log on a [`Progress`]: their lines as log lines, each embedding's steps as a
/// phase of its own.
pub(crate) struct BenchProgress {
    progress: Progress,
    what: String,
}

impl BenchProgress {
    pub(crate) fn new(mode: ProgressMode) -> Self {
        Self {
            progress: Progress::new(mode),
            what: String::new(),
        }
    }

    pub(crate) fn finish(&mut self) {
        self.progress.finish();
    }
}

impl crate::verify::BenchLog for BenchProgress {
    fn line(&mut self, text: &str) {
        self.progress.log_line(text);
    }

    fn step(&mut self, what: &str, step: usize, total: usize) {
        if what != self.what {
            self.what = what.to_string();
            self.progress.phase(what, total as u64);
        }
        self.progress.step(step as u64, "");
    }
}

/// A `Write` that hands each complete line to [`Progress::log_line`] (for code that logs to a
/// writer).
pub(crate) struct LogLines<'a> {
    progress: &'a std::cell::RefCell<Progress>,
    pending: Vec<u8>,
}

impl<'a> LogLines<'a> {
    pub(crate) fn new(progress: &'a std::cell::RefCell<Progress>) -> Self {
        Self {
            progress,
            pending: Vec::new(),
        }
    }
}

impl std::io::Write for LogLines<'_> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.pending.extend_from_slice(buf);
        while let Some(i) = self.pending.iter().position(|&c| c == b'\n') {
            let line: Vec<u8> = self.pending.drain(..=i).collect();
            self.progress
                .borrow()
                .log_line(String::from_utf8_lossy(&line[..i]).trim_end());
        }
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        if !self.pending.is_empty() {
            let line = std::mem::take(&mut self.pending);
            self.progress
                .borrow()
                .log_line(String::from_utf8_lossy(&line).trim_end());
        }
        Ok(())
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        self.finish_bar();
    }
}
