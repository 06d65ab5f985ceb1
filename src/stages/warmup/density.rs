//! Adaptive density control of 3DGS (Kerbl et al. 2023, §5.2): clone small Gaussians and split
//! large ones where the view-space positional gradient is large; prune transparent or
//! oversized ones; periodically reset opacities.

use glam::{Quat, Vec3};
use rand::Rng;

use super::adam::{AdamState, retain_rows};
use crate::scene::gaussians::Gaussians;

/// Per-Gaussian running statistics between densification steps.
#[derive(Debug, Clone, Default)]
pub struct DensityStats {
    /// Σ ‖∂L/∂μ₂D‖ in NDC units over the views where the Gaussian was visible.
    pub grad_sum: Vec<f32>,
    /// Number of such views.
    pub count: Vec<u32>,
    /// Largest screen radius seen (pixels).
    pub max_radius: Vec<f32>,
}

impl DensityStats {
    /// Zeroed statistics for `n` Gaussians.
    pub fn new(n: usize) -> Self {
        Self {
            grad_sum: vec![0.0; n],
            count: vec![0; n],
            max_radius: vec![0.0; n],
        }
    }

    /// Accumulate one view: pixel-space 2D-mean gradients are converted to NDC
    /// (`∂L/∂ndc = ∂L/∂px · size/2`, as 3DGS measures its threshold).
    pub fn add(&mut self, grad_px: &[[f32; 2]], radius: &[f32], width: u32, height: u32) {
        let (sx, sy) = (0.5 * width as f32, 0.5 * height as f32);
        for i in 0..self.count.len() {
            if radius[i] > 0.0 {
                let g = grad_px[i];
                self.grad_sum[i] += ((g[0] * sx).powi(2) + (g[1] * sy).powi(2)).sqrt();
                self.count[i] += 1;
                self.max_radius[i] = self.max_radius[i].max(radius[i]);
            }
        }
    }
}

/// Thresholds of one densification step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DensifyConfig {
    /// Mean NDC gradient above which a Gaussian is cloned or split (3DGS: 2e-4).
    pub grad_threshold: f32,
    /// Scale (fraction of the scene extent) separating clone from split (3DGS: 0.01).
    pub percent_dense: f32,
    /// Prune below this opacity (3DGS: 0.005).
    pub min_opacity: f32,
    /// Prune above this screen radius, pixels (0 = off).
    pub max_screen_radius: f32,
    /// Prune above this world scale, fraction of the extent.
    pub max_world_scale: f32,
    /// Scene extent, metres.
    pub extent: f32,
    /// Never exceed this many Gaussians.
    pub max_gaussians: usize,
}

/// Optimiser states of the parameter groups, kept in step with the Gaussians.
#[derive(Debug, Clone)]
pub struct GroupStates {
    /// Positions (3 per Gaussian).
    pub position: AdamState,
    /// Log-scales (3).
    pub log_scale: AdamState,
    /// Quaternions (4).
    pub rotation: AdamState,
    /// Opacity logits (1).
    pub opacity: AdamState,
    /// SH coefficients (3·(deg+1)²).
    pub sh: AdamState,
}

impl GroupStates {
    /// Zero states for `g`.
    pub fn new(g: &Gaussians) -> Self {
        let n = g.len();
        Self {
            position: AdamState::new(3, n),
            log_scale: AdamState::new(3, n),
            rotation: AdamState::new(4, n),
            opacity: AdamState::new(1, n),
            sh: AdamState::new(g.sh.len() / n.max(1), n),
        }
    }

    fn all(&mut self) -> [&mut AdamState; 5] {
        [
            &mut self.position,
            &mut self.log_scale,
            &mut self.rotation,
            &mut self.opacity,
            &mut self.sh,
        ]
    }
}

/// What a densification step did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DensifyReport {
    /// Gaussians duplicated in place.
    pub cloned: usize,
    /// Gaussians replaced by two smaller ones.
    pub split: usize,
    /// Gaussians removed.
    pub pruned: usize,
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// A standard normal sample (Box–Muller).
fn normal(rng: &mut impl Rng) -> f32 {
    let u1: f32 = rng.random::<f32>().max(1e-12);
    let u2: f32 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
}

/// Clone, split and prune. Statistics are consumed (reset by the caller).
pub fn densify(
    g: &mut Gaussians,
    states: &mut GroupStates,
    stats: &DensityStats,
    cfg: &DensifyConfig,
    rng: &mut impl Rng,
) -> DensifyReport {
    let n = g.len();
    let k = g.sh.len() / n.max(1);
    let mut report = DensifyReport::default();
    let room = cfg.max_gaussians.saturating_sub(n);
    let mut new_rows = 0usize;
    let mut split_src = vec![false; n];
    let max_scale = |i: usize| {
        g.log_scale[i]
            .iter()
            .cloned()
            .fold(f32::MIN, f32::max)
            .exp()
    };
    // Clones and splits append rows; originals of splits are removed below.
    let mut add = Gaussians {
        sh_degree: g.sh_degree,
        ..Default::default()
    };
    for (i, split) in split_src.iter_mut().enumerate() {
        if stats.count[i] == 0 || new_rows >= room {
            continue;
        }
        if stats.grad_sum[i] / (stats.count[i] as f32) < cfg.grad_threshold {
            continue;
        }
        if max_scale(i) <= cfg.percent_dense * cfg.extent {
            push_row(&mut add, g, i, k, g.position[i], g.log_scale[i]);
            report.cloned += 1;
            new_rows += 1;
        } else {
            let q = g.rotation[i];
            let rot = Quat::from_xyzw(q[1], q[2], q[3], q[0]).normalize();
            let s = Vec3::from(g.log_scale[i].map(f32::exp));
            let ls = g.log_scale[i].map(|l| l - 1.6f32.ln());
            for _ in 0..2 {
                let z = Vec3::new(normal(rng), normal(rng), normal(rng)) * s;
                let x = Vec3::from(g.position[i]) + rot * z;
                push_row(&mut add, g, i, k, x.to_array(), ls);
            }
            *split = true;
            report.split += 1;
            new_rows += 2;
        }
    }
    let added = add.len();
    g.id.extend((0..added as u32).map(|j| n as u32 + j));
    g.position.extend(add.position);
    g.log_scale.extend(add.log_scale);
    g.rotation.extend(add.rotation);
    g.opacity_logit.extend(add.opacity_logit);
    g.sh.extend(add.sh);
    g.simulated.extend(add.simulated);
    for s in states.all() {
        s.grow(added);
    }
    // Prune: split originals, transparent, and oversized Gaussians.
    let total = g.len();
    let keep: Vec<bool> = (0..total)
        .map(|i| {
            if i < n && split_src[i] {
                return false;
            }
            if sigmoid(g.opacity_logit[i]) < cfg.min_opacity {
                return false;
            }
            let big_screen =
                cfg.max_screen_radius > 0.0 && i < n && stats.max_radius[i] > cfg.max_screen_radius;
            let big_world = g.log_scale[i]
                .iter()
                .cloned()
                .fold(f32::MIN, f32::max)
                .exp()
                > cfg.max_world_scale * cfg.extent;
            !(big_screen || big_world)
        })
        .collect();
    report.pruned = keep.iter().filter(|k| !**k).count() - report.split;
    // Never prune everything: keep the scene renderable.
    if keep.iter().any(|k| *k) {
        retain(g, states, &keep);
    }
    report
}

fn push_row(add: &mut Gaussians, g: &Gaussians, i: usize, k: usize, x: [f32; 3], ls: [f32; 3]) {
    add.id.push(0);
    add.position.push(x);
    add.log_scale.push(ls);
    add.rotation.push(g.rotation[i]);
    add.opacity_logit.push(g.opacity_logit[i]);
    add.sh.extend_from_slice(&g.sh[i * k..(i + 1) * k]);
    add.simulated.push(g.simulated[i]);
}

/// Keep the flagged Gaussians (and their optimiser rows); ids are renumbered 0..n.
pub fn retain(g: &mut Gaussians, states: &mut GroupStates, keep: &[bool]) {
    let k = g.sh.len() / g.len().max(1);
    let pick = |v: &[[f32; 3]]| {
        v.iter()
            .zip(keep)
            .filter(|(_, k)| **k)
            .map(|(x, _)| *x)
            .collect::<Vec<_>>()
    };
    g.position = pick(&g.position);
    g.log_scale = pick(&g.log_scale);
    g.rotation = g
        .rotation
        .iter()
        .zip(keep)
        .filter(|(_, k)| **k)
        .map(|(x, _)| *x)
        .collect();
    g.opacity_logit = retain_rows(&g.opacity_logit, 1, keep);
    g.sh = retain_rows(&g.sh, k, keep);
    g.simulated = retain_rows(&g.simulated, 1, keep);
    g.id = (0..g.position.len() as u32).collect();
    for s in states.all() {
        s.retain(keep);
    }
}

/// 3DGS's opacity reset: clamp every opacity to at most `max_opacity`, zero its moments.
pub fn reset_opacity(g: &mut Gaussians, states: &mut GroupStates, max_opacity: f32) {
    let cap = (max_opacity / (1.0 - max_opacity)).ln();
    for o in &mut g.opacity_logit {
        *o = o.min(cap);
    }
    states.opacity.reset_all();
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn two() -> Gaussians {
        Gaussians {
            sh_degree: 0,
            id: vec![0, 1],
            position: vec![[0.0; 3], [1.0, 0.0, 0.0]],
            log_scale: vec![[0.001f32.ln(); 3], [0.5f32.ln(); 3]],
            rotation: vec![[1.0, 0.0, 0.0, 0.0]; 2],
            opacity_logit: vec![0.0, 0.0],
            sh: vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
            simulated: vec![true, true],
        }
    }

    fn cfg() -> DensifyConfig {
        DensifyConfig {
            grad_threshold: 1e-3,
            percent_dense: 0.01,
            min_opacity: 0.005,
            max_screen_radius: 0.0,
            max_world_scale: 10.0,
            extent: 1.0,
            max_gaussians: 100,
        }
    }

    #[test]
    fn small_high_gradient_gaussian_is_cloned_large_one_is_split() {
        let mut g = two();
        let mut st = GroupStates::new(&g);
        let stats = DensityStats {
            grad_sum: vec![1.0, 1.0],
            count: vec![1, 1],
            max_radius: vec![1.0, 1.0],
        };
        let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(1);
        let r = densify(&mut g, &mut st, &stats, &cfg(), &mut rng);
        assert_eq!(
            r,
            DensifyReport {
                cloned: 1,
                split: 1,
                pruned: 0
            }
        );
        // 2 - 1 (split original) + 1 (clone) + 2 (split children) = 4.
        assert_eq!(g.len(), 4);
        assert_eq!(g.sh.len(), 12);
        assert_eq!(st.sh.width, 3);
        // Split children are 1.6× smaller and keep the colour.
        let children: Vec<usize> = (0..4)
            .filter(|&i| (g.log_scale[i][0] - (0.5f32 / 1.6).ln()).abs() < 1e-6)
            .collect();
        assert_eq!(children.len(), 2);
        for &c in &children {
            assert_eq!(&g.sh[c * 3..c * 3 + 3], &[0.4, 0.5, 0.6]);
        }
        assert_eq!(g.id, vec![0, 1, 2, 3]);
    }

    #[test]
    fn low_gradient_does_nothing_and_transparent_is_pruned() {
        let mut g = two();
        g.opacity_logit[1] = -10.0;
        let mut st = GroupStates::new(&g);
        let stats = DensityStats::new(2);
        let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(1);
        let r = densify(&mut g, &mut st, &stats, &cfg(), &mut rng);
        assert_eq!(
            r,
            DensifyReport {
                cloned: 0,
                split: 0,
                pruned: 1
            }
        );
        assert_eq!(g.len(), 1);
    }

    #[test]
    fn opacity_reset_caps_opacities() {
        let mut g = two();
        g.opacity_logit = vec![5.0, -6.0];
        let mut st = GroupStates::new(&g);
        reset_opacity(&mut g, &mut st, 0.01);
        assert!((sigmoid(g.opacity_logit[0]) - 0.01).abs() < 1e-6);
        assert_eq!(g.opacity_logit[1], -6.0);
    }
}
