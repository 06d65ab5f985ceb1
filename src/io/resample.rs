//! Area resampling of 8-bit images to a smaller size: output pixel `(i, j)` of a `w2 × h2`
//! image is the mean of the input over the rectangle `[i·w/w2, (i+1)·w/w2) × [j·h/h2,
//! (j+1)·h/h2)` (pixel edges at integers, so pixel centres stay at `(i + ½, j + ½)` and a
//! point at continuous image coordinate `u` moves to `u·w2/w`: scale the intrinsics `fx, cx`
//! by `w2/w`, `fy, cy` by `h2/h`). Partly covered input pixels count by the area covered. For an
//! integer factor this is the box filter (each output the rounded mean of an `f × f` block).

/// The size an image of `width × height` takes at `scale` (0 < scale ≤ 1): each side
/// rounded, at least one pixel.
pub fn scaled_size(width: u32, height: u32, scale: f64) -> (u32, u32) {
    let side = |n: u32| ((f64::from(n) * scale).round() as u32).clamp(1, n);
    (side(width), side(height))
}

/// One axis: for every output pixel, the input pixels it covers and by how much.
fn axis_weights(n_in: u32, n_out: u32) -> Vec<Vec<(usize, f64)>> {
    let (n_in_f, n_out_f) = (f64::from(n_in), f64::from(n_out));
    (0..n_out)
        .map(|i| {
            let a = f64::from(i) * n_in_f / n_out_f;
            let b = f64::from(i + 1) * n_in_f / n_out_f;
            let (k0, k1) = (a.floor() as u32, (b.ceil() as u32).min(n_in));
            (k0..k1)
                .filter_map(|k| {
                    let w = (b.min(f64::from(k + 1)) - a.max(f64::from(k))).max(0.0);
                    (w > 0.0).then_some((k as usize, w))
                })
                .collect()
        })
        .collect()
}

/// Resamples `data` (`width × height` pixels of `channels` bytes, row-major) to `w2 × h2`
/// (each no larger than the input's) by area averaging.
///
/// # Panics
/// If `data` does not hold `width·height·channels` bytes or the new size is zero or larger.
pub fn area(data: &[u8], width: u32, height: u32, channels: usize, w2: u32, h2: u32) -> Vec<u8> {
    assert_eq!(
        data.len(),
        width as usize * height as usize * channels,
        "image data of the wrong length"
    );
    assert!(
        (1..=width).contains(&w2) && (1..=height).contains(&h2),
        "resampling {width}×{height} to {w2}×{h2}: only down"
    );
    if (w2, h2) == (width, height) {
        return data.to_vec();
    }
    let (wx, wy) = (axis_weights(width, w2), axis_weights(height, h2));
    let w = width as usize;
    let mut out = Vec::with_capacity(w2 as usize * h2 as usize * channels);
    let mut acc = vec![0.0f64; channels];
    for ry in &wy {
        for rx in &wx {
            acc.iter_mut().for_each(|a| *a = 0.0);
            let mut total = 0.0;
            for &(y, fy) in ry {
                for &(x, fx) in rx {
                    let weight = fy * fx;
                    total += weight;
                    let px = &data[(y * w + x) * channels..][..channels];
                    for (a, v) in acc.iter_mut().zip(px) {
                        *a += weight * f64::from(*v);
                    }
                }
            }
            out.extend(
                acc.iter()
                    .map(|a| (a / total + 0.5).floor().min(255.0) as u8),
            );
        }
    }
    out
}

/// A 0/255 mask resampled to `w2 × h2`: the covered fraction of each output pixel, thresholded
/// at one half (`≥ 128` of 255).
pub fn mask(data: &[u8], width: u32, height: u32, w2: u32, h2: u32) -> Vec<u8> {
    area(data, width, height, 1, w2, h2)
        .into_iter()
        .map(|v| if v >= 128 { 255 } else { 0 })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The rounded mean of each `f × f` block (remainders dropped), the textbook box filter.
    fn box_filter(data: &[u8], w: u32, h: u32, ch: usize, f: u32) -> Vec<u8> {
        let (w2, h2) = (w / f, h / f);
        let mut out = Vec::new();
        for y in 0..h2 {
            for x in 0..w2 {
                for c in 0..ch {
                    let mut s = 0u32;
                    for dy in 0..f {
                        for dx in 0..f {
                            let i = ((y * f + dy) * w + x * f + dx) as usize * ch + c;
                            s += u32::from(data[i]);
                        }
                    }
                    let n = f * f;
                    out.push(((s + n / 2) / n) as u8);
                }
            }
        }
        out
    }

    fn noise(n: usize, seed: u32) -> Vec<u8> {
        let mut s = seed;
        (0..n)
            .map(|_| {
                s = s.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                (s >> 24) as u8
            })
            .collect()
    }

    #[test]
    fn integer_factors_are_the_box_filter() {
        for (w, h, ch, f) in [(12, 9, 3, 3), (10, 8, 1, 2), (20, 20, 3, 4), (7, 7, 3, 7)] {
            let data = noise((w * h) as usize * ch, w * 31 + f);
            let got = area(&data, w, h, ch, w / f, h / f);
            assert_eq!(got, box_filter(&data, w, h, ch, f), "{w}×{h} by {f}");
        }
    }

    #[test]
    fn fractional_factors_keep_the_mean_and_the_constant() {
        let (w, h) = (30, 20);
        let flat = vec![77u8; (w * h * 3) as usize];
        let (w2, h2) = scaled_size(w, h, 0.7);
        assert_eq!((w2, h2), (21, 14));
        assert!(area(&flat, w, h, 3, w2, h2).iter().all(|v| *v == 77));
        // A left-half-white image: the mean brightness is kept within rounding.
        let half: Vec<u8> = (0..h)
            .flat_map(|_| (0..w).map(|x| if x < w / 2 { 255 } else { 0 }))
            .collect();
        let small = area(&half, w, h, 1, w2, h2);
        let mean = |v: &[u8]| v.iter().map(|x| f64::from(*x)).sum::<f64>() / v.len() as f64;
        assert!((mean(&small) - mean(&half)).abs() < 1.0);
        // The column straddling the edge (input x = 15 maps to 10.5) is half covered.
        assert_eq!(small[10], 128);
        assert_eq!(mask(&half, w, h, w2, h2)[10], 255);
        assert_eq!(mask(&half, w, h, w2, h2)[11], 0);
    }

    #[test]
    fn sizes_round_and_never_vanish() {
        assert_eq!(scaled_size(200, 200, 0.5), (100, 100));
        assert_eq!(scaled_size(201, 3, 0.5), (101, 2));
        assert_eq!(scaled_size(5, 5, 0.01), (1, 1));
        assert_eq!(scaled_size(5, 5, 1.0), (5, 5));
    }

    #[test]
    #[should_panic(expected = "wrong length")]
    fn a_short_buffer_is_refused() {
        area(&[0; 5], 2, 2, 3, 1, 1);
    }
}
