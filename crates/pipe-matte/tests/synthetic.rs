//! Synthetic-image checks of `pipe_matte::matte`: a textured floor plate, a shadow that
//! darkens it while keeping its texture and hue (must stay background), a blob with its
//! own colour and texture (must become foreground), isolated speckles (must vanish),
//! pinholes inside the object (must be filled) next to a real, large hole (must stay
//! open), a faint anti-aliased outline (must be peeled), plus degenerate inputs and the
//! error paths. Each case isolates one rule of the pipeline so that a regression points
//! at the rule that broke.

use pipe_matte::{Mask, MatteError, MatteParams, RgbImageView, iou, matte};

const W: usize = 96;
const H: usize = 80;

/// Deterministic hash noise in `0..=255`.
fn noise(x: usize, y: usize, salt: u32) -> u8 {
    let mut h = (x as u32).wrapping_mul(0x9E37_79B1) ^ (y as u32).wrapping_mul(0x85EB_CA77) ^ salt;
    h ^= h >> 15;
    h = h.wrapping_mul(0x2C1B_3C6D);
    h ^= h >> 12;
    (h & 0xFF) as u8
}

/// A beige tiled floor with dark grout lines and per-pixel grain, like the scenes' plates.
fn plate() -> Vec<u8> {
    let mut out = Vec::with_capacity(W * H * 3);
    for y in 0..H {
        for x in 0..W {
            let grout = x % 16 == 0 || y % 16 == 0;
            let tile = if (x / 16 + y / 16) % 2 == 0 { 1.0 } else { 0.8 };
            let grain = 0.9 + 0.2 * f32::from(noise(x, y, 1)) / 255.0;
            let s = if grout { 0.35 } else { tile * grain };
            for base in [170.0f32, 150.0, 118.0] {
                out.push((base * s).round() as u8);
            }
        }
    }
    out
}

fn in_disc(x: usize, y: usize, cx: f32, cy: f32, r: f32) -> bool {
    let (dx, dy) = (x as f32 + 0.5 - cx, y as f32 + 0.5 - cy);
    dx * dx + dy * dy <= r * r
}

/// Red/yellow striped object colour at `(x, y)`.
fn object_rgb(x: usize, y: usize) -> [u8; 3] {
    let g = noise(x, y, 7) / 8;
    if (x + y) % 8 < 4 {
        [200 + g / 2, 40 + g, 30]
    } else {
        [230, 200 + g, 60 + g]
    }
}

fn set(img: &mut [u8], x: usize, y: usize, rgb: [u8; 3]) {
    img[(y * W + x) * 3..(y * W + x) * 3 + 3].copy_from_slice(&rgb);
}

/// Multiplies the plate by `factor` (all channels) inside the disc.
fn shade(img: &mut [u8], cx: f32, cy: f32, r: f32, factor: f32) {
    for y in 0..H {
        for x in 0..W {
            if in_disc(x, y, cx, cy, r) {
                for c in 0..3 {
                    let v = &mut img[(y * W + x) * 3 + c];
                    *v = (f32::from(*v) * factor).round() as u8;
                }
            }
        }
    }
}

fn run(img: &[u8], plate: &[u8]) -> Mask {
    let i = RgbImageView::new(img, W, H).unwrap();
    let p = RgbImageView::new(plate, W, H).unwrap();
    matte(&i, &p, &MatteParams::default()).unwrap()
}

fn disc_mask(cx: f32, cy: f32, r: f32) -> Mask {
    let v: Vec<u8> = (0..W * H)
        .map(|p| {
            if in_disc(p % W, p / W, cx, cy, r) {
                255
            } else {
                0
            }
        })
        .collect();
    Mask::from_threshold(W, H, &v, 128).unwrap()
}

#[test]
fn identical_image_and_plate_give_empty_mask() {
    let p = plate();
    assert_eq!(run(&p, &p).count(), 0);
}

#[test]
fn textured_shadow_is_background() {
    let p = plate();
    for factor in [0.15, 0.4, 0.7] {
        let mut img = p.clone();
        shade(&mut img, 48.0, 40.0, 25.0, factor);
        let m = run(&img, &p);
        assert_eq!(m.count(), 0, "shadow x{factor} leaked {} pixels", m.count());
    }
}

#[test]
fn coloured_blob_is_foreground_and_its_shadow_is_not() {
    let p = plate();
    let mut img = p.clone();
    shade(&mut img, 56.0, 50.0, 20.0, 0.3);
    for y in 0..H {
        for x in 0..W {
            if in_disc(x, y, 40.0, 36.0, 18.0) {
                set(&mut img, x, y, object_rgb(x, y));
            }
        }
    }
    let score = iou(&run(&img, &p), &disc_mask(40.0, 36.0, 18.0));
    assert!(score >= 0.97, "IoU {score}");
}

#[test]
fn isolated_speckles_are_removed() {
    let p = plate();
    let mut img = p.clone();
    for (x, y) in [(5, 5), (30, 70), (90, 10), (60, 60), (61, 61)] {
        set(&mut img, x, y, [20, 220, 240]);
    }
    // A 3x3 cluster survives the majority vote but not the small-component filter.
    for y in 20..23 {
        for x in 70..73 {
            set(&mut img, x, y, [20, 220, 240]);
        }
    }
    assert_eq!(run(&img, &p).count(), 0);
}

#[test]
fn pinhole_filled_but_real_hole_kept() {
    let p = plate();
    let mut img = p.clone();
    // Ring (torus seen face-on): outer radius 30, inner radius 10.
    let (cx, cy) = (48.0, 40.0);
    for y in 0..H {
        for x in 0..W {
            if in_disc(x, y, cx, cy, 30.0) && !in_disc(x, y, cx, cy, 10.0) {
                set(&mut img, x, y, object_rgb(x, y));
            }
        }
    }
    // Pinholes where the object happens to match the plate: single pixels and pairs
    // (closed by the majority vote) and a 5-pixel plus whose centre survives the vote
    // and needs the small-hole filling.
    let pinholes = [
        (30, 40),
        (31, 40),
        (66, 40),
        (48, 60),
        (48, 18),
        (47, 18),
        (49, 18),
        (48, 17),
        (48, 19),
    ];
    for (x, y) in pinholes {
        let o = (y * W + x) * 3;
        img[o..o + 3].copy_from_slice(&p[o..o + 3]);
    }
    let m = run(&img, &p);
    for (x, y) in pinholes {
        assert!(m.get(x, y), "pinhole ({x}, {y}) not filled");
    }
    assert!(!m.get(48, 40), "real hole of the ring was filled");
    let ring: Vec<u8> = (0..W * H)
        .map(|q| {
            let (x, y) = (q % W, q / W);
            if in_disc(x, y, cx, cy, 30.0) && !in_disc(x, y, cx, cy, 10.0) {
                255
            } else {
                0
            }
        })
        .collect();
    let score = iou(&m, &Mask::from_threshold(W, H, &ring, 128).unwrap());
    assert!(score >= 0.97, "IoU {score}");
}

#[test]
fn degenerate_inputs_do_not_panic() {
    let params = MatteParams::default();
    for (w, h) in [(0, 0), (1, 1), (1, 7), (7, 1), (2, 2)] {
        let black = vec![0u8; w * h * 3];
        let white = vec![255u8; w * h * 3];
        let b = RgbImageView::new(&black, w, h).unwrap();
        let wv = RgbImageView::new(&white, w, h).unwrap();
        assert_eq!(matte(&b, &b, &params).unwrap().count(), 0);
        let m = matte(&wv, &b, &params).unwrap();
        assert_eq!((m.width(), m.height(), m.data().len()), (w, h, w * h));
        assert!(m.data().iter().all(|&v| v == 0 || v == 255));
    }
}

#[test]
fn errors_name_the_sizes() {
    let buf = vec![0u8; 10];
    let err = RgbImageView::new(&buf, 2, 2).unwrap_err();
    assert_eq!(
        err,
        MatteError::BufferLength {
            width: 2,
            height: 2,
            channels: 3,
            expected: 12,
            actual: 10
        }
    );
    assert!(err.to_string().contains("2x2") && err.to_string().contains("12"));

    let a = vec![0u8; 12];
    let b = vec![0u8; 18];
    let err = matte(
        &RgbImageView::new(&a, 2, 2).unwrap(),
        &RgbImageView::new(&b, 3, 2).unwrap(),
        &MatteParams::default(),
    )
    .unwrap_err();
    assert!(
        err.to_string().contains("2x2") && err.to_string().contains("3x2"),
        "{err}"
    );

    assert!(matches!(
        RgbImageView::new(&a, usize::MAX, 2),
        Err(MatteError::DimensionOverflow { .. })
    ));
    assert!(Mask::from_threshold(3, 3, &a, 128).is_err());
}

#[test]
fn iou_edge_cases() {
    let e = Mask::empty(4, 4).unwrap();
    assert_eq!(iou(&e, &e), 1.0);
    let full = Mask::from_threshold(4, 4, &[255; 16], 128).unwrap();
    assert_eq!(iou(&e, &full), 0.0);
    let half: Vec<u8> = (0..16).map(|i| if i < 8 { 200 } else { 10 }).collect();
    let half = Mask::from_threshold(4, 4, &half, 128).unwrap();
    assert_eq!(iou(&half, &full), 0.5);
    assert_eq!(iou(&half, &Mask::empty(2, 8).unwrap()), 0.0);
}

#[test]
fn deterministic() {
    let p = plate();
    let mut img = p.clone();
    shade(&mut img, 50.0, 50.0, 20.0, 0.3);
    for y in 10..40 {
        for x in 10..50 {
            set(&mut img, x, y, object_rgb(x, y));
        }
    }
    let a = run(&img, &p);
    for _ in 0..4 {
        assert_eq!(run(&img, &p), a);
    }
}

#[test]
fn faint_antialiased_outline_is_peeled() {
    // A uniformly blue square covering x, y in 30..60, surrounded by a one-pixel ring of
    // 15 %-coverage blends (weak change, but still a hue change above the noise
    // threshold). The ring is background under the alpha >= 0.5 convention.
    let p = plate();
    let mut img = p.clone();
    let blue = [40.0f32, 110.0, 200.0];
    for y in 29..61 {
        for x in 29..61 {
            let cover = if (30..60).contains(&x) && (30..60).contains(&y) {
                1.0
            } else {
                0.15
            };
            let o = (y * W + x) * 3;
            for c in 0..3 {
                img[o + c] = (cover * blue[c] + (1.0 - cover) * f32::from(p[o + c])).round() as u8;
            }
        }
    }
    let truth: Vec<u8> = (0..W * H)
        .map(|q| {
            if (30..60).contains(&(q % W)) && (30..60).contains(&(q / W)) {
                255
            } else {
                0
            }
        })
        .collect();
    let m = run(&img, &p);
    assert_eq!(m, Mask::from_threshold(W, H, &truth, 128).unwrap());
}
