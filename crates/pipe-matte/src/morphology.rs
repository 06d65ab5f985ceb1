//! Binary morphology on row-major boolean images.

use rayon::prelude::*;

/// 3x3 majority vote: a pixel is set iff at least 5 of the 9 pixels of its 3x3
/// neighbourhood (itself included; pixels outside the image count as unset) are set.
///
/// Removes one-pixel speckles and spurs and fills one-pixel notches, i.e. it smooths the
/// boundary without shifting straight edges.
pub(crate) fn majority3(bits: &[bool], width: usize, height: usize) -> Vec<bool> {
    let mut out = vec![false; bits.len()];
    if width == 0 || height == 0 {
        return out;
    }
    out.par_chunks_mut(width).enumerate().for_each(|(y, row)| {
        let y0 = y.saturating_sub(1);
        let y1 = (y + 1).min(height - 1);
        for (x, o) in row.iter_mut().enumerate() {
            let x0 = x.saturating_sub(1);
            let x1 = (x + 1).min(width - 1);
            let mut n = 0;
            for yy in y0..=y1 {
                n += bits[yy * width + x0..=yy * width + x1]
                    .iter()
                    .filter(|&&b| b)
                    .count();
            }
            *o = n >= 5;
        }
    });
    out
}

/// Boundary peel: an object pixel with a background 4-neighbour (pixels outside the
/// image count as object) is cleared iff `strength <= threshold`.
///
/// Pixels on the outline are usually partly covered; the colour change of a pixel with
/// less than half coverage is typically small, so the outline demands stronger evidence
/// than the interior.
pub(crate) fn peel_weak_boundary(
    bits: &[bool],
    strength: &[u8],
    width: usize,
    height: usize,
    threshold: u8,
) -> Vec<bool> {
    let mut out = bits.to_vec();
    if width == 0 || height == 0 {
        return out;
    }
    out.par_chunks_mut(width).enumerate().for_each(|(y, row)| {
        for (x, o) in row.iter_mut().enumerate() {
            let p = y * width + x;
            if !bits[p] || strength[p] > threshold {
                continue;
            }
            let on_outline = (x > 0 && !bits[p - 1])
                || (x + 1 < width && !bits[p + 1])
                || (y > 0 && !bits[p - width])
                || (y + 1 < height && !bits[p + width]);
            if on_outline {
                *o = false;
            }
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn speckle_removed_and_notch_filled() {
        let (w, h) = (7, 7);
        let mut bits = vec![false; w * h];
        bits[w + 1] = true; // isolated speckle
        for y in 3..7 {
            for x in 2..7 {
                bits[y * w + x] = true;
            }
        }
        bits[4 * w + 4] = false; // one-pixel hole
        let out = majority3(&bits, w, h);
        assert!(!out[w + 1]);
        assert!(out[4 * w + 4]);
        assert!(out[5 * w + 3]);
    }

    #[test]
    fn peel_removes_only_weak_outline_pixels() {
        let (w, h) = (5, 5);
        let bits: Vec<bool> = (0..w * h)
            .map(|p| (1..4).contains(&(p % w)) && (1..4).contains(&(p / w)))
            .collect();
        let mut strength = vec![10u8; w * h];
        strength[w + 1] = 200; // strong outline pixel survives
        let out = peel_weak_boundary(&bits, &strength, w, h, 24);
        assert!(out[w + 1], "strong outline pixel kept");
        assert!(!out[w + 2], "weak outline pixel peeled");
        assert!(out[2 * w + 2], "weak interior pixel kept");
        // Pixels touching the image border only are not on the outline.
        let full = vec![true; 4];
        assert_eq!(peel_weak_boundary(&full, &[0; 4], 2, 2, 24), full);
    }

    #[test]
    fn tiny_images() {
        assert!(majority3(&[], 0, 0).is_empty());
        assert_eq!(majority3(&[true], 1, 1), vec![false]);
    }
}
