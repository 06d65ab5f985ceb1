//! The length of a field's step, searched on the loss: Adam gives the direction (its step at
//! the scheduled rate), and multiples `t` of it are tried, longest first, until one lowers the
//! loss. The first multiple tried doubles after a step taken at it (up to [`MAX_SCALE`]) and
//! follows the step taken otherwise; when none lowers the loss the field stays, and the next
//! search starts shorter. A field's first steps at a safe rate are short (the output layer
//! starts at zero), and a rate that is fast early overshoots later: the search serves both.

/// Trials per search (each half the last).
pub const TRIALS: i32 = 3;
/// The longest multiple of Adam's step tried.
pub const MAX_SCALE: f64 = 16.0;

/// The search's state across epochs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepSearch {
    /// The multiple of Adam's step tried first.
    pub scale: f64,
}

impl Default for StepSearch {
    fn default() -> Self {
        Self { scale: 1.0 }
    }
}

impl StepSearch {
    /// Tries `t = scale, scale/2, …` ([`TRIALS`] of them) through `loss_at(t)` (the loss with
    /// the step scaled by `t`; `None` when that step cannot be evaluated) and returns the first
    /// `(t, loss)` below `loss0`, or `None`. A trial is rejected whatever its loss above
    /// `loss0`: `loss_at` may stop early and return any value at or above it.
    ///
    /// # Errors
    /// The first error of `loss_at`.
    pub fn run<E>(
        &mut self,
        loss0: f64,
        mut loss_at: impl FnMut(f64) -> Result<Option<f64>, E>,
    ) -> Result<Option<(f64, f64)>, E> {
        for trial in 0..TRIALS {
            let t = self.scale * 0.5f64.powi(trial);
            if let Some(l) = loss_at(t)?
                && l < loss0
            {
                self.scale = if trial == 0 {
                    (2.0 * t).min(MAX_SCALE)
                } else {
                    t
                };
                return Ok(Some((t, l)));
            }
        }
        self.scale *= 0.5f64.powi(TRIALS);
        Ok(None)
    }
}

/// Epochs over which a field's loss must fall by [`STALL_FRACTION`] of itself for its fit to
/// go on.
pub const STALL_WINDOW: usize = 3;
/// See [`STALL_WINDOW`].
pub const STALL_FRACTION: f64 = 1e-3;

/// Whether a fit whose loss at the start of each epoch was `losses` has stalled: over the last
/// [`STALL_WINDOW`] epochs the loss fell by less than [`STALL_FRACTION`] of itself (a field
/// that explains nothing more than the global model, e.g. a velocity field over a rigid
/// throw, stops after a few epochs instead of running them all).
pub fn stalled(losses: &[f64]) -> bool {
    let n = losses.len();
    n > STALL_WINDOW && {
        let (old, new) = (losses[n - 1 - STALL_WINDOW], losses[n - 1]);
        old - new < STALL_FRACTION * old.abs()
    }
}

/// The log line of a `what` fit that [`stalled`] after `epoch` (1-based) of `epochs`.
pub fn stall_note(what: &str, epoch: u32, epochs: u32) -> String {
    format!(
        "{what}: stopped after epoch {epoch} of {epochs}: the loss fell less than {} % over {STALL_WINDOW} epochs",
        STALL_FRACTION * 100.0
    )
}

/// `a + t·(b − a)`, element by element.
pub fn lerp(a: &[f64], b: &[f64], t: f64) -> Vec<f64> {
    a.iter().zip(b).map(|(a, b)| a + t * (b - a)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_search_grows_after_success_and_shrinks_after_failure() {
        // A parabola with its minimum at t = 3: t = 1 lowers the loss, so does 2, then 4 …
        let f = |t: f64| (t - 3.0) * (t - 3.0);
        let mut s = StepSearch::default();
        let r = s.run::<()>(f(0.0), |t| Ok(Some(f(t)))).unwrap();
        assert_eq!(r, Some((1.0, 4.0)));
        assert_eq!(s.scale, 2.0);
        // From t = 0 again with the loss at 0 of 9: 2 is accepted (loss 1), scale 4.
        assert_eq!(
            s.run::<()>(9.0, |t| Ok(Some(f(t)))).unwrap(),
            Some((2.0, 1.0))
        );
        assert_eq!(s.scale, 4.0);
        // Nothing lowers a loss of 0: three trials, the scale drops by 8.
        let mut tried = Vec::new();
        let r = s
            .run::<()>(0.0, |t| {
                tried.push(t);
                Ok(Some(f(t)))
            })
            .unwrap();
        assert_eq!(r, None);
        assert_eq!(tried, vec![4.0, 2.0, 1.0]);
        assert_eq!(s.scale, 0.5);
        // A trial that cannot be evaluated is skipped; an error stops the search.
        assert_eq!(
            s.run::<()>(9.0, |t| Ok((t < 0.5).then(|| f(t)))).unwrap(),
            Some((0.25, f(0.25)))
        );
        assert_eq!(s.run(9.0, |_| Err("boom")), Err("boom"));
        assert_eq!(lerp(&[0.0, 2.0], &[1.0, 4.0], 0.5), vec![0.5, 3.0]);
    }

    #[test]
    fn a_fit_stalls_when_three_epochs_gain_less_than_a_thousandth() {
        assert!(!stalled(&[1.0, 1.0, 1.0]));
        assert!(stalled(&[1.0, 1.0, 1.0, 1.0]));
        assert!(stalled(&[1.0, 0.9999, 0.9998, 0.99905]));
        assert!(!stalled(&[1.0, 0.9999, 0.9998, 0.9985]));
        // Only the last window counts; a loss that rose has stalled.
        assert!(!stalled(&[2.0, 1.0, 0.9, 0.8, 0.7]));
        assert!(stalled(&[2.0, 1.0, 0.9, 0.9, 1.0]));
    }
}
