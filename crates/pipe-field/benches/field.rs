//! Timings of a field's forward, and forward + backward (the gradient of every weight), on
//! 20 000 pseudo-random points in a 1 m box, for the material defaults (24² planes, 16 summed
//! channels, 2 × 64 ReLU, 2 outputs) and the velocity defaults (8² planes, 3 outputs). Run with
//! `cargo bench -p pipe-field --bench field`.

use divan::Bencher;
use pipe_field::{Domain, Field, FieldConfig};

const POINTS: usize = 20_000;

fn points(n: usize) -> Vec<[f64; 3]> {
    let mut state = 7u64;
    let mut next = move || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((state >> 11) as f64) / (1u64 << 53) as f64
    };
    (0..n).map(|_| [next(), next(), next()]).collect()
}

fn field(config: &FieldConfig) -> Field {
    let domain = Domain::new([0.0; 3], [1.0; 3]).unwrap();
    Field::new(config, domain, 1).unwrap()
}

fn configs(which: &str) -> FieldConfig {
    match which {
        "material" => FieldConfig::material(2),
        _ => FieldConfig::velocity(3),
    }
}

#[divan::bench(args = ["material", "velocity"], sample_count = 10)]
fn forward(b: Bencher, which: &str) {
    let f = field(&configs(which));
    let x = points(POINTS);
    b.bench_local(|| f.forward(&x).unwrap());
}

#[divan::bench(args = ["material", "velocity"], sample_count = 10)]
fn forward_backward(b: Bencher, which: &str) {
    let f = field(&configs(which));
    let x = points(POINTS);
    let d_out: Vec<f64> = (0..POINTS * f.outputs())
        .map(|i| ((i % 7) as f64 - 3.0) * 0.1)
        .collect();
    b.bench_local(|| {
        let y = f.forward(&x).unwrap();
        let g = f.backward(&x, &d_out).unwrap();
        (y, g)
    });
}

fn main() {
    divan::main();
}
