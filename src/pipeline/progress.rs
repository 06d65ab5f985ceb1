//! Progress reporting: indicatif bars on a terminal, plain log lines otherwise.

use std::sync::Mutex;
use std::time::{Duration, Instant};

use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};

/// What a stage may report while it runs.
pub trait Progress: Send + Sync {
    /// Start a unit of work with `total` steps (e.g. epochs, images).
    fn start(&self, label: &str, total: u64);
    /// `n` more steps done.
    fn inc(&self, n: u64);
    /// A short status (e.g. `loss 0.031  psnr 29.4`).
    fn message(&self, msg: &str);
    /// A line for the log.
    fn log(&self, line: &str);
    /// A line the user must see even with `--quiet` (resuming from a checkpoint, warnings).
    fn notice(&self, line: &str) {
        self.log(line);
    }
    /// A warning: printed as `warning: LINE` even with `--quiet` (which only drops progress).
    fn warn(&self, line: &str) {
        self.notice(&format!("warning: {line}"));
    }
}

/// A stage's progress: passed on to the run's reporter, its warnings also kept for the stage's
/// manifest (so that `pipe report` shows them after the terminal has scrolled away).
pub struct Recording<'a> {
    inner: &'a dyn Progress,
    warnings: Mutex<Vec<String>>,
}

impl std::fmt::Debug for Recording<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recording")
            .field("warnings", &self.warnings())
            .finish()
    }
}

impl<'a> Recording<'a> {
    /// Passes everything on to `inner`.
    pub fn new(inner: &'a dyn Progress) -> Self {
        Self {
            inner,
            warnings: Mutex::new(Vec::new()),
        }
    }

    /// The warnings given so far, in order.
    pub fn warnings(&self) -> Vec<String> {
        self.warnings.lock().expect("not poisoned").clone()
    }
}

impl Progress for Recording<'_> {
    fn start(&self, label: &str, total: u64) {
        self.inner.start(label, total);
    }
    fn inc(&self, n: u64) {
        self.inner.inc(n);
    }
    fn message(&self, msg: &str) {
        self.inner.message(msg);
    }
    fn log(&self, line: &str) {
        self.inner.log(line);
    }
    fn notice(&self, line: &str) {
        self.inner.notice(line);
    }
    fn warn(&self, line: &str) {
        self.warnings
            .lock()
            .expect("not poisoned")
            .push(line.to_string());
        self.inner.warn(line);
    }
}

/// How the run talks to the user.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// Live bars (stderr is a terminal).
    Bars,
    /// One line per stage event and a few per unit of work.
    Plain,
    /// Stage start/finish lines only.
    Quiet,
}

struct PlainState {
    label: String,
    total: u64,
    done: u64,
    last: Instant,
    msg: String,
}

/// The runner's reporter: one stage bar plus one work bar, or log lines.
pub struct Reporter {
    mode: Mode,
    multi: MultiProgress,
    stage_bar: Mutex<Option<ProgressBar>>,
    work_bar: Mutex<Option<ProgressBar>>,
    plain: Mutex<PlainState>,
}

impl std::fmt::Debug for Reporter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Reporter")
            .field("mode", &self.mode)
            .finish()
    }
}

impl Reporter {
    /// A reporter in `mode`.
    pub fn new(mode: Mode) -> Self {
        let multi = MultiProgress::with_draw_target(if mode == Mode::Bars {
            ProgressDrawTarget::stderr()
        } else {
            ProgressDrawTarget::hidden()
        });
        Self {
            mode,
            multi,
            stage_bar: Mutex::new(None),
            work_bar: Mutex::new(None),
            plain: Mutex::new(PlainState {
                label: String::new(),
                total: 0,
                done: 0,
                last: Instant::now(),
                msg: String::new(),
            }),
        }
    }

    /// Bars when stdout and stderr are terminals and not `quiet`; plain lines otherwise.
    pub fn auto(quiet: bool) -> Self {
        use std::io::IsTerminal;
        let mode = if quiet {
            Mode::Quiet
        } else if std::io::stdout().is_terminal() && std::io::stderr().is_terminal() {
            Mode::Bars
        } else {
            Mode::Plain
        };
        Self::new(mode)
    }

    /// Print a line above the bars (or plainly).
    pub fn println(&self, line: &str) {
        if self.mode == Mode::Bars {
            let _ = self.multi.println(line);
        } else {
            eprintln!("{line}");
        }
    }

    /// A stage begins (`i` of `n`).
    pub fn stage_started(&self, i: usize, n: usize, name: &str) {
        if self.mode == Mode::Bars {
            let bar = self.multi.add(ProgressBar::new(n as u64));
            bar.set_style(
                ProgressStyle::with_template(
                    "{prefix:>10.bold} [{elapsed_precise}] stage {pos}/{len} {msg}",
                )
                .expect("valid template"),
            );
            bar.set_prefix("pipe");
            bar.set_position(i as u64);
            bar.set_message(name.to_string());
            bar.enable_steady_tick(Duration::from_millis(200));
            *self.stage_bar.lock().expect("not poisoned") = Some(bar);
        } else {
            eprintln!("[{}/{}] {name}: running", i + 1, n);
        }
    }

    /// A stage ended; `outcome` says how (`done in 3.2 s`, `cached`, `FAILED`).
    pub fn stage_finished(&self, i: usize, n: usize, name: &str, outcome: &str) {
        if let Some(b) = self.work_bar.lock().expect("not poisoned").take() {
            b.finish_and_clear();
        }
        if let Some(b) = self.stage_bar.lock().expect("not poisoned").take() {
            b.finish_and_clear();
        }
        self.println(&format!("[{}/{}] {name}: {outcome}", i + 1, n));
    }
}

impl Progress for Reporter {
    fn start(&self, label: &str, total: u64) {
        match self.mode {
            Mode::Bars => {
                let bar = self.multi.add(ProgressBar::new(total));
                bar.set_style(
                    ProgressStyle::with_template(
                        "{prefix:>10} {bar:30} {pos}/{len} {per_sec} eta {eta} {msg}",
                    )
                    .expect("valid template"),
                );
                bar.set_prefix(label.to_string());
                if let Some(old) = self.work_bar.lock().expect("not poisoned").replace(bar) {
                    old.finish_and_clear();
                }
            }
            Mode::Plain | Mode::Quiet => {
                let mut s = self.plain.lock().expect("not poisoned");
                s.label = label.to_string();
                s.total = total;
                s.done = 0;
                s.last = Instant::now();
                s.msg.clear();
            }
        }
    }

    fn inc(&self, n: u64) {
        match self.mode {
            Mode::Bars => {
                if let Some(b) = &*self.work_bar.lock().expect("not poisoned") {
                    b.inc(n);
                }
            }
            Mode::Plain => {
                let mut s = self.plain.lock().expect("not poisoned");
                s.done += n;
                let finished = s.done >= s.total;
                if finished || s.last.elapsed() >= Duration::from_secs(5) {
                    s.last = Instant::now();
                    eprintln!("    {} {}/{} {}", s.label, s.done, s.total, s.msg);
                }
            }
            Mode::Quiet => {}
        }
    }

    fn message(&self, msg: &str) {
        match self.mode {
            Mode::Bars => {
                if let Some(b) = &*self.work_bar.lock().expect("not poisoned") {
                    b.set_message(msg.to_string());
                }
            }
            Mode::Plain | Mode::Quiet => {
                self.plain.lock().expect("not poisoned").msg = msg.to_string()
            }
        }
    }

    fn log(&self, line: &str) {
        if self.mode != Mode::Quiet {
            self.println(&format!("    {line}"));
        }
    }

    fn notice(&self, line: &str) {
        self.println(&format!("    {line}"));
    }
}
