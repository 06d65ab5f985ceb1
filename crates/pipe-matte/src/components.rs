//! 4-connected component analysis: dropping small blobs and filling small holes.

/// Labels the 4-connected components of pixels equal to `value`.
///
/// Returns per-pixel labels (`usize::MAX` for pixels not equal to `value`) and, per label,
/// its area and whether it touches the image border.
fn label(
    bits: &[bool],
    width: usize,
    height: usize,
    value: bool,
) -> (Vec<usize>, Vec<(usize, bool)>) {
    let mut labels = vec![usize::MAX; bits.len()];
    let mut comps: Vec<(usize, bool)> = Vec::new();
    let mut stack = Vec::new();
    for start in 0..bits.len() {
        if bits[start] != value || labels[start] != usize::MAX {
            continue;
        }
        let id = comps.len();
        let (mut area, mut border) = (0usize, false);
        labels[start] = id;
        stack.push(start);
        while let Some(p) = stack.pop() {
            area += 1;
            let (x, y) = (p % width, p / width);
            border |= x == 0 || y == 0 || x + 1 == width || y + 1 == height;
            let mut visit = |q: usize| {
                if bits[q] == value && labels[q] == usize::MAX {
                    labels[q] = id;
                    stack.push(q);
                }
            };
            if x > 0 {
                visit(p - 1);
            }
            if x + 1 < width {
                visit(p + 1);
            }
            if y > 0 {
                visit(p - width);
            }
            if y + 1 < height {
                visit(p + width);
            }
        }
        comps.push((area, border));
    }
    (labels, comps)
}

/// Clears every 4-connected object component with fewer than `min_area` pixels.
pub(crate) fn remove_small_components(
    bits: &mut [bool],
    width: usize,
    height: usize,
    min_area: usize,
) {
    if min_area <= 1 {
        return;
    }
    let (labels, comps) = label(bits, width, height, true);
    for (b, &l) in bits.iter_mut().zip(&labels) {
        if let Some(&(area, _)) = comps.get(l) {
            *b &= area >= min_area;
        }
    }
}

/// Sets every hole — a 4-connected background component that does not touch the image
/// border, hence is enclosed by object — with at most `max_area` pixels.
///
/// Large holes are kept on purpose: objects such as a torus have real ones.
pub(crate) fn fill_small_holes(bits: &mut [bool], width: usize, height: usize, max_area: usize) {
    if max_area == 0 {
        return;
    }
    let (labels, comps) = label(bits, width, height, false);
    for (b, &l) in bits.iter_mut().zip(&labels) {
        if let Some(&(area, border)) = comps.get(l) {
            *b |= !border && area <= max_area;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square(w: usize, h: usize, x0: usize, x1: usize, y0: usize, y1: usize) -> Vec<bool> {
        (0..w * h)
            .map(|p| (x0..x1).contains(&(p % w)) && (y0..y1).contains(&(p / w)))
            .collect()
    }

    #[test]
    fn small_components_dropped_large_kept() {
        let (w, h) = (10, 10);
        let mut bits = square(w, h, 4, 9, 4, 9);
        bits[0] = true;
        bits[w + 1] = true; // diagonal neighbour: separate 4-component
        remove_small_components(&mut bits, w, h, 2);
        assert!(!bits[0] && !bits[w + 1]);
        assert_eq!(bits.iter().filter(|&&b| b).count(), 25);
    }

    #[test]
    fn small_holes_filled_large_and_open_kept() {
        let (w, h) = (12, 12);
        let mut bits = square(w, h, 1, 11, 1, 11);
        bits[3 * w + 3] = false; // 1-pixel hole
        for y in 6..10 {
            for x in 6..10 {
                bits[y * w + x] = false; // 16-pixel hole
            }
        }
        fill_small_holes(&mut bits, w, h, 4);
        assert!(bits[3 * w + 3]);
        assert!(!bits[7 * w + 7]);
        assert!(!bits[0], "border background is never a hole");
    }

    #[test]
    fn empty_inputs() {
        let mut none: Vec<bool> = Vec::new();
        remove_small_components(&mut none, 0, 0, 10);
        fill_small_holes(&mut none, 0, 0, 10);
        let mut one = vec![true];
        remove_small_components(&mut one, 1, 1, 2);
        assert_eq!(one, vec![false]);
    }
}
