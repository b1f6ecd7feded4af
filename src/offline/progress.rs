//! Signs of life on long jobs (map building, imports, evaluations): a progress bar on stderr when it is a
//! terminal (indicatif), plain log lines at every tenth of the work otherwise (CI, a redirected log).

use std::io::IsTerminal;
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};

/// The progress of one job of `total` steps.
pub struct Progress {
    bar: Option<ProgressBar>,
    label: String,
    total: u64,
    done: u64,
    /// The next step at which a log line is written (without a terminal), and the last one written.
    next_line: u64,
    logged: u64,
    started: Instant,
}

impl Progress {
    pub fn new(label: impl Into<String>, total: usize) -> Self {
        let label = label.into();
        let total = total as u64;
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar = ProgressBar::new(total);
            let style = ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} ({elapsed}, {eta} left)")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> ");
            bar.set_style(style);
            bar.set_message(label.clone());
            bar
        });
        Self { bar, label, total, done: 0, next_line: total.div_ceil(10).max(1), logged: 0, started: Instant::now() }
    }

    /// One more step done.
    pub fn step(&mut self) {
        self.set(self.done as usize + 1);
    }

    /// `done` steps done so far (a job counted in units it does not take one at a time, e.g. observations).
    pub fn set(&mut self, done: usize) {
        self.done = (done as u64).min(self.total);
        match &self.bar {
            Some(bar) => bar.set_position(self.done),
            None if self.done > self.logged && (self.done >= self.next_line || self.done == self.total) => {
                tracing::info!(job = %self.label, done = self.done, total = self.total,
                    seconds = self.started.elapsed().as_secs(), "progress");
                self.logged = self.done;
                self.next_line = self.done + self.total.div_ceil(10).max(1);
            }
            None => {}
        }
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_steps_and_positions_within_the_total() {
        let mut p = Progress::new("test", 15);
        for _ in 0..14 {
            p.step();
        }
        assert_eq!(p.done, 14);
        p.set(40);
        assert_eq!((p.done, p.logged), (15, 15), "the last step is logged once, and never beyond the total");
        p.set(15);
        assert_eq!(p.logged, 15);
    }
}
