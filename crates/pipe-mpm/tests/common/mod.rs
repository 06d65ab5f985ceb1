//! Shared loader of the PAC-NeRF MPM fixtures (`tests/fixtures/*.json`).
#![allow(dead_code)]

use glam::{DMat3, DVec3};
use pipe_mpm::math::{from_rows, max_abs};
use pipe_mpm::{Aabb, Boundaries, BoundaryKind, Collider, Material, SimConfig, State, StateGrad};
use serde_json::Value;

/// One fixture file, parsed.
pub struct Fixture {
    pub json: Value,
    pub fluid: bool,
    pub dx: f64,
    pub dt: f64,
    pub n_substeps: usize,
    pub initial: State,
    pub material: Material,
    pub after1: State,
    pub final_: State,
    pub loss_w: Vec<DVec3>,
    pub grads: StateGrad,
    pub grad_mass: Vec<f64>,
    pub grad_mu: Vec<f64>,
    pub grad_lam: Vec<f64>,
}

pub fn load(name: &str) -> Fixture {
    let path = format!("{}/tests/fixtures/{name}.json", env!("CARGO_MANIFEST_DIR"));
    let json: Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    let fluid = json["initial"].get("J").is_some();
    let c = &json["constants"];
    let dx = c["dx"].as_f64().unwrap();
    let dt = c["dt"].as_f64().unwrap();
    let n_substeps = c["n_substeps"].as_u64().unwrap() as usize;
    let p_vol = c["p_vol"].as_f64().unwrap();
    let ini = &json["initial"];
    let initial = state(ini, fluid, true);
    let n = initial.len();
    let material = Material {
        mass: f32s(&ini["mass"]),
        volume: vec![p_vol; n],
        mu: f64s(&ini["mu_p"]),
        lam: f64s(&ini["lam_p"]),
        family: Vec::new(),
    };
    let g = &json["grads"];
    let grads = StateGrad {
        x: vecs(&g["x0"], false),
        v: vecs(&g["v0"], false),
        c: mats(&g["C0"], false),
        f: if fluid {
            js(&g["J0"], false)
        } else {
            mats(&g["F0"], false)
        },
    };
    Fixture {
        fluid,
        dx,
        dt,
        n_substeps,
        after1: state(&json["after_substep_1"], fluid, false),
        final_: state(&json["final"], fluid, false),
        loss_w: vecs(&json["loss"]["W"], true),
        grad_mass: f64s(&g["mass"]),
        grad_mu: f64s(&g["mu_p"]),
        grad_lam: f64s(&g["lam_p"]),
        grads,
        initial,
        material,
        json,
    }
}

impl Fixture {
    /// PAC-NeRF's scene: gravity, sticky ground y = 0, no walls, domain [0, 1]³.
    pub fn config(&self) -> SimConfig {
        let mut cfg = SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), self.dx, self.dt);
        cfg.gravity = DVec3::new(0.0, -9.8, 0.0);
        cfg.boundaries = Boundaries {
            colliders: vec![Collider::ground(0.0, BoundaryKind::Sticky)],
            walls: None,
        };
        cfg
    }

    pub fn param(&self, key: &str) -> f64 {
        self.json["params"][key].as_f64().unwrap()
    }

    pub fn grad(&self, key: &str) -> f64 {
        self.json["grads"][key].as_f64().unwrap()
    }

    /// Loss seed `∂L/∂x_final = W`.
    pub fn seed(&self) -> StateGrad {
        let mut g = StateGrad::zeros(self.initial.len());
        g.x.clone_from(&self.loss_w);
        g
    }
}

fn num(v: &Value, as_f32: bool) -> f64 {
    let x = v.as_f64().unwrap();
    if as_f32 { x as f32 as f64 } else { x }
}

fn f32s(v: &Value) -> Vec<f64> {
    v.as_array().unwrap().iter().map(|x| num(x, true)).collect()
}

fn f64s(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| num(x, false))
        .collect()
}

fn vecs(v: &Value, as_f32: bool) -> Vec<DVec3> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|r| {
            let r = r.as_array().unwrap();
            DVec3::new(num(&r[0], as_f32), num(&r[1], as_f32), num(&r[2], as_f32))
        })
        .collect()
}

fn mats(v: &Value, as_f32: bool) -> Vec<DMat3> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|m| {
            let rows = m.as_array().unwrap();
            let mut out = [[0.0; 3]; 3];
            for (i, r) in rows.iter().enumerate() {
                for (j, x) in r.as_array().unwrap().iter().enumerate() {
                    out[i][j] = num(x, as_f32);
                }
            }
            from_rows(out)
        })
        .collect()
}

fn js(v: &Value, as_f32: bool) -> Vec<DMat3> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|j| {
            let mut m = DMat3::ZERO;
            m.x_axis.x = num(j, as_f32);
            m
        })
        .collect()
}

fn jmats(v: &Value, as_f32: bool) -> Vec<DMat3> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|j| DMat3::from_diagonal(DVec3::new(num(j, as_f32), 1.0, 1.0)))
        .collect()
}

fn state(v: &Value, fluid: bool, as_f32: bool) -> State {
    State {
        x: vecs(&v["x"], as_f32),
        v: vecs(&v["v"], as_f32),
        c: mats(&v["C"], as_f32),
        f: if fluid {
            jmats(&v["J"], as_f32)
        } else {
            mats(&v["F"], as_f32)
        },
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

/// Panics unless the two arrays compared by `what` have the same length (a missing gradient
/// or particle must not pass as a match of the common prefix).
fn same_len(what: &str, a: usize, b: usize) {
    assert_eq!(a, b, "{what}: the arrays have {a} and {b} elements");
}

/// Largest absolute component of a vector; NaN if a component is NaN.
fn vec_max_abs(v: DVec3) -> f64 {
    if v.is_nan() {
        f64::NAN
    } else {
        v.abs().max_element()
    }
}

/// Max abs difference of two vector arrays (panics on NaN or a length mismatch).
pub fn max_diff_v(a: &[DVec3], b: &[DVec3]) -> f64 {
    same_len("max_diff_v", a.len(), b.len());
    max_checked(
        "max_diff_v",
        a.iter().zip(b).map(|(x, y)| vec_max_abs(*x - *y)),
    )
}

/// Max abs difference of two matrix arrays (panics on NaN or a length mismatch).
pub fn max_diff_m(a: &[DMat3], b: &[DMat3]) -> f64 {
    same_len("max_diff_m", a.len(), b.len());
    max_checked(
        "max_diff_m",
        a.iter().zip(b).map(|(x, y)| max_abs(&(*x - *y))),
    )
}

/// Max abs entry of a vector array (panics on NaN).
pub fn max_abs_v(a: &[DVec3]) -> f64 {
    max_checked("max_abs_v", a.iter().map(|x| vec_max_abs(*x)))
}

/// Max abs entry of a matrix array (panics on NaN).
pub fn max_abs_m(a: &[DMat3]) -> f64 {
    max_checked("max_abs_m", a.iter().map(max_abs))
}

/// Max abs difference of two scalar arrays (panics on NaN or a length mismatch).
pub fn max_diff_s(a: &[f64], b: &[f64]) -> f64 {
    same_len("max_diff_s", a.len(), b.len());
    max_checked("max_diff_s", a.iter().zip(b).map(|(x, y)| (x - y).abs()))
}

/// Max abs entry of a scalar array (panics on NaN).
pub fn max_abs_s(a: &[f64]) -> f64 {
    max_checked("max_abs_s", a.iter().map(|x| x.abs()))
}

/// A 4×4×4 block of particles at spacing `dx/2` thrown down at 1 m/s, with particle 0 placed
/// on the domain edge (x = 0): the scene of the extreme-parameter tests.
pub fn thrown_block(dx: f64) -> State {
    let mut x = Vec::new();
    for i in 0..4 {
        for j in 0..4 {
            for k in 0..4 {
                x.push(
                    DVec3::new(0.4, 0.03, 0.4)
                        + DVec3::new(i as f64, j as f64, k as f64) * (dx / 2.0),
                );
            }
        }
    }
    x[0] = DVec3::new(0.0, 0.03, 0.4); // on the domain edge
    let mut s = State::at_rest(x);
    s.v.iter_mut().for_each(|v| *v = DVec3::new(0.0, -1.0, 0.0));
    s
}
