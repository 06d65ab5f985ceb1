//! Adam (Kingma & Ba 2015) over flat f32 parameter rows, with the row bookkeeping that
//! densification needs (drop rows, append zero-state rows).

/// First and second moments of one parameter group, `width` values per Gaussian.
#[derive(Debug, Clone, PartialEq)]
pub struct AdamState {
    /// Values per row (Gaussian).
    pub width: usize,
    m: Vec<f32>,
    v: Vec<f32>,
}

/// Adam hyper-parameters (3DGS: β₁ = 0.9, β₂ = 0.999, ε = 1e-15).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamConfig {
    /// Decay of the first moment.
    pub beta1: f32,
    /// Decay of the second moment.
    pub beta2: f32,
    /// Denominator guard.
    pub eps: f32,
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-15,
        }
    }
}

impl AdamState {
    /// Zero moments for `rows` rows of `width` values.
    pub fn new(width: usize, rows: usize) -> Self {
        Self {
            width,
            m: vec![0.0; width * rows],
            v: vec![0.0; width * rows],
        }
    }

    /// One step at iteration `t` (1-based): `p ← p − lr·m̂/(√v̂ + ε)`. `lr_of(k)` gives the rate of
    /// value `k` within a row (for per-coefficient rates, e.g. SH DC vs. higher orders).
    pub fn step(
        &mut self,
        cfg: &AdamConfig,
        t: u32,
        params: &mut [f32],
        grads: &[f32],
        lr_of: impl Fn(usize) -> f32,
    ) {
        debug_assert_eq!(params.len(), self.m.len());
        debug_assert_eq!(grads.len(), self.m.len());
        let bc1 = 1.0 - cfg.beta1.powi(t as i32);
        let bc2 = 1.0 - cfg.beta2.powi(t as i32);
        let lrs: Vec<f32> = (0..self.width).map(&lr_of).collect();
        for (i, ((p, g), (m, v))) in params
            .iter_mut()
            .zip(grads)
            .zip(self.m.iter_mut().zip(self.v.iter_mut()))
            .enumerate()
        {
            *m = cfg.beta1 * *m + (1.0 - cfg.beta1) * g;
            *v = cfg.beta2 * *v + (1.0 - cfg.beta2) * g * g;
            let m_hat = *m / bc1;
            let v_hat = *v / bc2;
            *p -= lrs[i % self.width] * m_hat / (v_hat.sqrt() + cfg.eps);
        }
    }

    /// Keep only rows whose `keep` flag is set.
    pub fn retain(&mut self, keep: &[bool]) {
        self.m = retain_rows(&self.m, self.width, keep);
        self.v = retain_rows(&self.v, self.width, keep);
    }

    /// Append `rows` rows of zero moments (new Gaussians start fresh, as in 3DGS).
    pub fn grow(&mut self, rows: usize) {
        self.m.resize(self.m.len() + rows * self.width, 0.0);
        self.v.resize(self.v.len() + rows * self.width, 0.0);
    }

    /// Zero the moments of one row (e.g. after an opacity reset).
    pub fn reset_all(&mut self) {
        self.m.fill(0.0);
        self.v.fill(0.0);
    }
}

/// The rows of `data` (`width` values each) whose flag is set.
pub fn retain_rows<T: Copy>(data: &[T], width: usize, keep: &[bool]) -> Vec<T> {
    data.chunks_exact(width)
        .zip(keep)
        .filter(|(_, k)| **k)
        .flat_map(|(row, _)| row.iter().copied())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn minimises_a_quadratic() {
        // f(p) = Σ (p - 3)², gradient 2(p - 3).
        let mut p = vec![0.0f32, 10.0];
        let mut s = AdamState::new(1, 2);
        let cfg = AdamConfig::default();
        for t in 1..=2000 {
            let g: Vec<f32> = p.iter().map(|x| 2.0 * (x - 3.0)).collect();
            s.step(&cfg, t, &mut p, &g, |_| 0.05);
        }
        assert!(p.iter().all(|x| (x - 3.0).abs() < 1e-2), "{p:?}");
    }

    #[test]
    fn first_step_moves_by_the_learning_rate() {
        let mut p = vec![1.0f32, 1.0, 1.0];
        let mut s = AdamState::new(3, 1);
        s.step(&AdamConfig::default(), 1, &mut p, &[0.5, -2.0, 0.0], |k| {
            [0.1, 0.2, 0.3][k]
        });
        assert!(
            (p[0] - 0.9).abs() < 1e-6 && (p[1] - 1.2).abs() < 1e-6 && p[2] == 1.0,
            "{p:?}"
        );
    }

    #[test]
    fn rows_are_kept_and_grown() {
        assert_eq!(
            retain_rows(&[1, 2, 3, 4, 5, 6], 2, &[true, false, true]),
            vec![1, 2, 5, 6]
        );
        let mut s = AdamState::new(2, 3);
        s.retain(&[true, false, true]);
        s.grow(4);
        assert_eq!(s.m.len(), 12);
    }
}
