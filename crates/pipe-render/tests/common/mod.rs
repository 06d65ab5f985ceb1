//! Shared helpers of the pipe-render tests: fixture loading and small random scenes.
#![allow(dead_code)]

use pipe_render::{Camera, Real};
use serde_json::Value;

/// Parses a fixture file from `tests/fixtures/`.
pub fn load(name: &str) -> Value {
    let path = format!("{}/tests/fixtures/{name}", env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
    serde_json::from_str(&text).unwrap()
}

/// Flattens a nested JSON array of numbers (or booleans as 0/1) into f64.
pub fn flat(v: &Value) -> Vec<f64> {
    let mut out = Vec::new();
    fn rec(v: &Value, out: &mut Vec<f64>) {
        match v {
            Value::Array(a) => a.iter().for_each(|x| rec(x, out)),
            Value::Number(n) => out.push(n.as_f64().unwrap()),
            Value::Bool(b) => out.push(if *b { 1.0 } else { 0.0 }),
            other => panic!("unexpected {other}"),
        }
    }
    rec(v, &mut out);
    out
}

/// Flattens and reads each number as f32 first (the fixture inputs are f32-exact), then
/// converts to `T`.
pub fn flat_input<T: Real>(v: &Value) -> Vec<T> {
    flat(v)
        .into_iter()
        .map(|x| T::from_f64(x as f32 as f64))
        .collect()
}

pub fn chunks<T: Copy, const N: usize>(v: &[T]) -> Vec<[T; N]> {
    v.chunks_exact(N)
        .map(|c| std::array::from_fn(|i| c[i]))
        .collect()
}

/// Camera of a raster fixture.
pub fn fixture_camera<T: Real>(inp: &Value) -> Camera<T> {
    let k = flat_input::<T>(&inp["K"]);
    let vm = flat_input::<T>(&inp["viewmat"]);
    Camera {
        camera_from_world_rotation: std::array::from_fn(|r| std::array::from_fn(|c| vm[r * 4 + c])),
        camera_from_world_translation: [vm[3], vm[7], vm[11]],
        fx: k[0],
        fy: k[4],
        cx: k[2],
        cy: k[5],
        width: inp["W"].as_u64().unwrap() as u32,
        height: inp["H"].as_u64().unwrap() as u32,
        near: T::from_f64(inp["near"].as_f64().unwrap() as f32 as f64),
    }
}

/// The largest of `values` (0 for none). Panics on a NaN, naming `what` and the element:
/// `f64::max` would drop it, and a NaN would pass any tolerance.
pub fn max_checked(what: &str, values: impl IntoIterator<Item = f64>) -> f64 {
    values.into_iter().enumerate().fold(0.0, |m, (i, v)| {
        assert!(!v.is_nan(), "{what}: element {i} is NaN");
        m.max(v)
    })
}

/// Max of |a - b| over all entries; panics on NaN and when the lengths differ (a missing
/// gradient must not pass as a match of the common prefix).
pub fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(
        a.len(),
        b.len(),
        "max_abs_diff: the arrays have {} and {} elements",
        a.len(),
        b.len()
    );
    max_checked("max_abs_diff", a.iter().zip(b).map(|(x, y)| (x - y).abs()))
}

/// Max of |a| over all entries; panics on NaN.
pub fn max_abs(a: &[f64]) -> f64 {
    max_checked("max_abs", a.iter().map(|x| x.abs()))
}

/// SplitMix64: tiny deterministic PRNG for test and bench scenes.
#[derive(Debug, Clone)]
pub struct Rng(pub u64);

impl Rng {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }
    /// Standard normal (Box–Muller).
    pub fn normal(&mut self) -> f64 {
        let u1 = self.uniform().max(1e-300);
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

/// Owned Gaussian parameters in the trainable parameterisation.
#[derive(Debug, Clone)]
pub struct Scene<T> {
    pub means: Vec<[T; 3]>,
    pub log_scales: Vec<[T; 3]>,
    pub quats: Vec<[T; 4]>,
    pub logits: Vec<T>,
    pub rgb: Vec<[T; 3]>,
    pub sh_degree: u32,
    pub sh: Vec<[T; 3]>,
}

impl<T: Real> Scene<T> {
    pub fn gaussians_rgb(&self) -> pipe_render::Gaussians<'_, T> {
        pipe_render::Gaussians {
            means: &self.means,
            scales: pipe_render::Scales::Log(&self.log_scales),
            quats: &self.quats,
            opacities: pipe_render::Opacities::Logit(&self.logits),
            colors: pipe_render::Colors::Rgb(&self.rgb),
            deformation: None,
        }
    }
    pub fn gaussians_sh(&self) -> pipe_render::Gaussians<'_, T> {
        pipe_render::Gaussians {
            colors: pipe_render::Colors::Sh {
                degree: self.sh_degree,
                coeffs: &self.sh,
            },
            ..self.gaussians_rgb()
        }
    }
}

/// Camera at the origin looking down +z with horizontal FOV `hfov_deg`, principal point at
/// the image centre.
pub fn simple_camera<T: Real>(width: u32, height: u32, hfov_deg: f64) -> Camera<T> {
    let f = 0.5 * width as f64 / (0.5 * hfov_deg.to_radians()).tan();
    let i = |r: usize, c: usize| if r == c { T::ONE } else { T::ZERO };
    Camera {
        camera_from_world_rotation: std::array::from_fn(|r| std::array::from_fn(|c| i(r, c))),
        camera_from_world_translation: [T::ZERO; 3],
        fx: T::from_f64(f),
        fy: T::from_f64(f),
        cx: T::from_f64(0.5 * width as f64),
        cy: T::from_f64(0.5 * height as f64),
        width,
        height,
        near: T::from_f64(0.01),
    }
}

/// The anchor workload: means uniform in [-1.6,1.6]²×[3,5], log-uniform scales in
/// [0.005, 0.03], random unit quaternions, opacity U(0.1, 0.9), RGB U(0, 1).
pub fn anchor_scene<T: Real>(n: usize, seed: u64, sh_degree: u32) -> Scene<T> {
    let mut rng = Rng(seed);
    let f = T::from_f64;
    let mut s = Scene {
        means: Vec::with_capacity(n),
        log_scales: Vec::with_capacity(n),
        quats: Vec::with_capacity(n),
        logits: Vec::with_capacity(n),
        rgb: Vec::with_capacity(n),
        sh_degree,
        sh: Vec::new(),
    };
    let k = ((sh_degree + 1) * (sh_degree + 1)) as usize;
    for _ in 0..n {
        s.means.push([
            f(rng.range(-1.6, 1.6)),
            f(rng.range(-1.6, 1.6)),
            f(rng.range(3.0, 5.0)),
        ]);
        s.log_scales.push(std::array::from_fn(|_| {
            f(rng.range(0.005f64.ln(), 0.03f64.ln()))
        }));
        let q: [f64; 4] = std::array::from_fn(|_| rng.normal());
        let qn = q.iter().map(|x| x * x).sum::<f64>().sqrt();
        s.quats.push(q.map(|x| f(x / qn)));
        let o = rng.range(0.1, 0.9);
        s.logits.push(f((o / (1.0 - o)).ln()));
        s.rgb.push(std::array::from_fn(|_| f(rng.uniform())));
        for j in 0..k {
            let scale = if j == 0 { 1.0 } else { 0.3 };
            s.sh.push(std::array::from_fn(|_| f(scale * rng.range(-1.0, 1.0))));
        }
    }
    s
}
