//! Adam fits the material-default field (24² planes, 16 channels, 2 × 64 ReLU) to a known
//! two-region function: log10 E = 5 for x < 0 and 6.5 for x > 0 over a 2 m × 0.4 m × 0.4 m bar,
//! with a second output (encoded ν) that stays at 0.3. The field starts at the global fit
//! (the constant 5.75, 0.3), as the material stage will start it; the loss is the mean squared
//! error plus the plane TV. Checked on held-out points: the median log10 E of each half is
//! within 0.15 of its truth, and the second output stays within 0.05 of 0.3.

use pipe_field::{AdamConfig, Domain, Field, FieldAdam, FieldConfig, LrSchedule};

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

fn bar_points(n: usize, seed: u64) -> Vec<[f64; 3]> {
    let mut r = Lcg(seed);
    (0..n)
        .map(|_| {
            [
                2.0 * r.uniform() - 1.0,
                0.4 * r.uniform(),
                0.4 * r.uniform(),
            ]
        })
        .collect()
}

fn truth(x: &[f64; 3]) -> [f64; 2] {
    [if x[0] < 0.0 { 5.0 } else { 6.5 }, 0.3]
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Mean squared error over points and outputs, and `∂/∂y`.
fn mse(field: &Field, x: &[[f64; 3]]) -> (f64, Vec<f64>) {
    let y = field.forward(x).unwrap();
    let n = y.len() as f64;
    let mut loss = 0.0;
    let mut d = vec![0.0; y.len()];
    for (i, p) in x.iter().enumerate() {
        for (k, t) in truth(p).into_iter().enumerate() {
            let r = y[2 * i + k] - t;
            loss += r * r / n;
            d[2 * i + k] = 2.0 * r / n;
        }
    }
    (loss, d)
}

#[test]
fn adam_fits_a_two_region_function() {
    let domain = Domain::around(&bar_points(2000, 1), 0.05).unwrap();
    let config = FieldConfig::material(2);
    let mut field = Field::with_constant_output(&config, domain, 7, &[5.75, 0.3]).unwrap();
    let steps = 100;
    let mut adam = FieldAdam::new(
        &field,
        LrSchedule::exponential(3e-2, 3e-3, steps),
        LrSchedule::exponential(3e-3, 3e-4, steps),
        AdamConfig::default(),
    )
    .unwrap();
    let train = bar_points(1000, 2);
    let (initial, _) = mse(&field, &train);
    let mut last = initial;
    for _ in 0..steps {
        let (loss, d) = mse(&field, &train);
        let mut g = field.backward(&train, &d).unwrap();
        let tv = field.tv_backward(&mut g).unwrap();
        assert!(loss.is_finite() && tv.is_finite());
        adam.step(&mut field, &g).unwrap();
        last = loss;
    }
    assert_eq!(adam.adam().steps(), steps);

    let test = bar_points(2000, 3);
    let y = field.forward(&test).unwrap();
    let (mut left, mut right, mut second) = (vec![], vec![], vec![]);
    for (p, row) in test.iter().zip(y.chunks_exact(2)) {
        if p[0] < 0.0 {
            left.push(row[0]);
        } else {
            right.push(row[0]);
        }
        second.push(row[1]);
    }
    let (ml, mr, m2) = (median(left), median(right), median(second));
    eprintln!(
        "mse {initial:.3e} -> {last:.3e}; median log10 E left {ml:.4} right {mr:.4}; second {m2:.4}"
    );
    assert!((ml - 5.0).abs() < 0.15, "left half median {ml}");
    assert!((mr - 6.5).abs() < 0.15, "right half median {mr}");
    assert!((m2 - 0.3).abs() < 0.05, "second output median {m2}");
    assert!(last < 0.1 * initial, "mse {initial} -> {last}");
}
