//! f64 central finite differences against the hand-written backward, for every weight of a
//! small field (every plane feature, MLP weight and bias), for `∂L/∂x`, and for the TV term.
//!
//! The loss is `L = Σ_i g_i · y(x_i)` with fixed pseudo-random `g` (so `∂L/∂y = g`), over 12
//! points inside a non-cubic, off-origin box and 2 outside it (clamped). Step `h = 1e-5`;
//! a derivative passes when `|analytic − fd| ≤ 1e-6 · max(|analytic|, |fd|) + 1e-9` (L is
//! O(1), so 1e-9 is the absolute floor for derivatives that are zero or nearly so). Both
//! activations and both plane combinations are checked.

use pipe_field::{Activation, Combine, Domain, Field, FieldConfig};

const H: f64 = 1e-5;
const REL: f64 = 1e-6;
const ABS: f64 = 1e-9;

struct Lcg(u64);
impl Lcg {
    fn uniform(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64) / (1u64 << 53) as f64
    }
}

fn config(combine: Combine, activation: Activation) -> FieldConfig {
    FieldConfig {
        resolution: 4,
        channels: 3,
        combine,
        hidden: 5,
        layers: 2,
        activation,
        outputs: 2,
        tv_weight: 0.3,
        plane_init: 0.5,
    }
}

fn domain() -> Domain {
    Domain::new([-0.5, 0.0, -1.0], [1.5, 1.0, 2.0]).unwrap()
}

/// 12 points inside the box, then 2 outside it (clamped on some axes).
fn points() -> Vec<[f64; 3]> {
    let mut r = Lcg(11);
    let (lo, hi) = (domain().min(), domain().max());
    let mut p: Vec<[f64; 3]> = (0..12)
        .map(|_| std::array::from_fn(|a| lo[a] + (hi[a] - lo[a]) * r.uniform()))
        .collect();
    p.push([2.5, 0.3, -3.0]);
    p.push([0.1, -7.0, 1.2]);
    p
}

fn loss(field: &Field, x: &[[f64; 3]], g: &[f64]) -> f64 {
    let y = field.forward(x).unwrap();
    y.iter().zip(g).map(|(a, b)| a * b).sum()
}

fn close(analytic: f64, fd: f64) -> bool {
    (analytic - fd).abs() <= REL * analytic.abs().max(fd.abs()) + ABS
}

/// Every weight's derivative; returns how many were nonzero in each of planes / weights /
/// biases so the caller can check the test exercised them.
fn check_weights(combine: Combine, activation: Activation) {
    let mut field = Field::new(&config(combine, activation), domain(), 3).unwrap();
    let x = points();
    let mut r = Lcg(5);
    let g: Vec<f64> = (0..x.len() * 2).map(|_| r.uniform() * 2.0 - 1.0).collect();
    let grad = field.backward(&x, &g).unwrap().to_flat();
    let flat = field.to_flat();
    assert_eq!(grad.len(), flat.len());

    // Which flat index is which kind.
    let planes = field.triplane().values().len();
    let mut kind = vec!["plane feature"; planes];
    kind.resize(flat.len(), "");
    for (_, _, w, b) in field.mlp().layer_ranges() {
        for k in w {
            kind[planes + k] = "mlp weight";
        }
        for k in b {
            kind[planes + k] = "mlp bias";
        }
    }
    assert!(kind.iter().all(|k| !k.is_empty()));

    let mut largest = std::collections::BTreeMap::<&str, f64>::new();
    for k in 0..flat.len() {
        let mut p = flat.clone();
        p[k] = flat[k] + H;
        field.set_flat(&p).unwrap();
        let up = loss(&field, &x, &g);
        p[k] = flat[k] - H;
        field.set_flat(&p).unwrap();
        let down = loss(&field, &x, &g);
        let fd = (up - down) / (2.0 * H);
        assert!(
            close(grad[k], fd),
            "{combine:?}/{activation:?}: {} {k}: analytic {} vs fd {fd}",
            kind[k],
            grad[k]
        );
        let m = largest.entry(kind[k]).or_default();
        *m = m.max(grad[k].abs());
    }
    field.set_flat(&flat).unwrap();
    // Each kind was exercised with gradients well above the tolerance floor.
    for kind in ["plane feature", "mlp weight", "mlp bias"] {
        assert!(largest[kind] > 1e-3, "{kind}: largest |grad| {largest:?}");
    }
}

#[test]
fn every_weight_gradient_matches_finite_differences_sum_relu() {
    check_weights(Combine::Sum, Activation::Relu);
}

#[test]
fn every_weight_gradient_matches_finite_differences_concat_relu() {
    check_weights(Combine::Concat, Activation::Relu);
}

#[test]
fn every_weight_gradient_matches_finite_differences_sum_softplus() {
    check_weights(Combine::Sum, Activation::Softplus);
}

#[test]
fn every_weight_gradient_matches_finite_differences_concat_softplus() {
    check_weights(Combine::Concat, Activation::Softplus);
}

#[test]
fn point_gradients_match_finite_differences_and_vanish_where_clamped() {
    for (combine, activation) in [
        (Combine::Sum, Activation::Softplus),
        (Combine::Concat, Activation::Relu),
    ] {
        let field = Field::new(&config(combine, activation), domain(), 4).unwrap();
        let x = points();
        let mut r = Lcg(9);
        let g: Vec<f64> = (0..x.len() * 2).map(|_| r.uniform() * 2.0 - 1.0).collect();
        let (_, dx) = field.backward_with_points(&x, &g).unwrap();
        for (i, p) in x.iter().enumerate() {
            // Per-point loss: other points do not move.
            let gi = &g[2 * i..2 * i + 2];
            for a in 0..3 {
                let mut q = *p;
                q[a] = p[a] + H;
                let up = loss(&field, &[q], gi);
                q[a] = p[a] - H;
                let down = loss(&field, &[q], gi);
                let fd = (up - down) / (2.0 * H);
                assert!(
                    close(dx[i][a], fd),
                    "{combine:?}/{activation:?}: point {i} axis {a}: analytic {} vs fd {fd}",
                    dx[i][a]
                );
            }
        }
        // The outside points are clamped on x and z (point 12) and on y (point 13).
        assert_eq!(dx[12][0], 0.0);
        assert_eq!(dx[12][2], 0.0);
        assert_eq!(dx[13][1], 0.0);
        assert!(dx[12][1] != 0.0 && dx[13][0] != 0.0);
    }
}

#[test]
fn tv_gradient_matches_finite_differences() {
    let field = Field::new(&config(Combine::Sum, Activation::Relu), domain(), 8).unwrap();
    let planes = field.triplane();
    let w = field.config().tv_weight;
    let mut grad = vec![0.0; planes.values().len()];
    let value = planes.tv_backward(w, &mut grad);
    assert_eq!(value, planes.tv(w));
    assert!(value > 0.0);
    let mut t = planes.clone();
    for (k, analytic) in grad.iter().enumerate() {
        let v = t.values()[k];
        t.values_mut()[k] = v + H;
        let up = t.tv(w);
        t.values_mut()[k] = v - H;
        let down = t.tv(w);
        t.values_mut()[k] = v;
        let fd = (up - down) / (2.0 * H);
        assert!(
            close(*analytic, fd),
            "tv: feature {k}: analytic {analytic} vs fd {fd}"
        );
    }
    // Field::tv_backward adds the same gradient into a FieldGradient.
    let mut fg = pipe_field::FieldGradient::zeros(&field);
    assert_eq!(field.tv_backward(&mut fg).unwrap(), value);
    assert_eq!(fg.planes, grad);
}

#[test]
fn tv_of_constant_planes_is_zero_and_of_a_ramp_is_known() {
    let mut t = pipe_field::Triplane::zeros(3, 2, Combine::Sum).unwrap();
    t.values_mut().fill(0.7);
    assert_eq!(t.tv(1.0), 0.0);
    // A ramp along i with step 1 on every plane and channel: horizontal mean = 1, vertical 0,
    // summed over 3 planes = 3.
    for p in 0..3 {
        for j in 0..3 {
            for i in 0..3 {
                for c in 0..2 {
                    let k = t.index(p, j, i, c);
                    t.values_mut()[k] = i as f64;
                }
            }
        }
    }
    assert_eq!(t.tv(2.0), 6.0);
}
