//! The dataset scenes' ground truth (`tests/fixtures/trajectories/<scene>`: `params.json` and
//! the particles of some frames), shared by the trajectory and identification tests.
#![allow(dead_code)]

use glam::DVec3;
use serde_json::Value;

pub fn dir(scene: &str) -> String {
    format!(
        "{}/tests/fixtures/trajectories/{scene}",
        env!("CARGO_MANIFEST_DIR")
    )
}

/// Binary little-endian PLY with exactly `float x, y, z` per vertex.
pub fn read_ply(path: &str) -> Vec<DVec3> {
    let bytes = std::fs::read(path).unwrap();
    let end = b"end_header\n";
    let pos = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
    let header = std::str::from_utf8(&bytes[..pos]).unwrap();
    assert!(header.contains("binary_little_endian") && header.contains("property float z"));
    let n: usize = header
        .lines()
        .find_map(|l| l.strip_prefix("element vertex "))
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    let data = &bytes[pos..];
    assert_eq!(data.len(), n * 12);
    let f = |i: usize| f32::from_le_bytes(data[4 * i..4 * i + 4].try_into().unwrap()) as f64;
    (0..n)
        .map(|p| DVec3::new(f(3 * p), f(3 * p + 1), f(3 * p + 2)))
        .collect()
}

pub fn params(scene: &str) -> Value {
    serde_json::from_str(&std::fs::read_to_string(format!("{}/params.json", dir(scene))).unwrap())
        .unwrap()
}

pub fn arr3(v: &Value) -> DVec3 {
    DVec3::new(
        v[0].as_f64().unwrap(),
        v[1].as_f64().unwrap(),
        v[2].as_f64().unwrap(),
    )
}
