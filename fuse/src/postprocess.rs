//! Post-processing of disparity maps.

use rayon::prelude::*;

use crate::image::DisparityImage;

/// 3×3 median of the valid values around each pixel (invalid pixels stay invalid). Rows run in
/// parallel; a pixel whose nine values are all valid goes through a 19-exchange sorting network,
/// the others (borders, next to invalid pixels) through a sort of their valid values.
pub fn median3x3(input: &DisparityImage) -> DisparityImage {
    let (w, h) = (input.width, input.height);
    let mut data = input.data.clone();
    data.par_chunks_mut(w).enumerate().for_each(|(y, out)| {
        let mut window = Vec::with_capacity(9);
        let rows = [y.saturating_sub(1), y, (y + 1).min(h - 1)].map(|r| &input.data[r * w..(r + 1) * w]);
        for (x, value) in out.iter_mut().enumerate() {
            if !value.is_finite() {
                continue;
            }
            if y > 0 && y + 1 < h && x > 0 && x + 1 < w {
                let mut p = [
                    rows[0][x - 1],
                    rows[0][x],
                    rows[0][x + 1],
                    rows[1][x - 1],
                    rows[1][x],
                    rows[1][x + 1],
                    rows[2][x - 1],
                    rows[2][x],
                    rows[2][x + 1],
                ];
                if p.iter().all(|v| v.is_finite()) {
                    *value = median_of_nine(&mut p);
                    continue;
                }
            }
            window.clear();
            for yy in y.saturating_sub(1)..(y + 2).min(h) {
                for xx in x.saturating_sub(1)..(x + 2).min(w) {
                    let v = input.data[yy * w + xx];
                    if v.is_finite() {
                        window.push(v);
                    }
                }
            }
            window.sort_unstable_by(f32::total_cmp);
            *value = window[window.len() / 2];
        }
    });
    DisparityImage {
        width: w,
        height: h,
        data,
    }
}

/// The median of nine finite values by the 19 compare-exchanges of Paeth's network.
#[inline]
fn median_of_nine(p: &mut [f32; 9]) -> f32 {
    const EXCHANGES: [(usize, usize); 19] = [
        (1, 2),
        (4, 5),
        (7, 8),
        (0, 1),
        (3, 4),
        (6, 7),
        (1, 2),
        (4, 5),
        (7, 8),
        (0, 3),
        (5, 8),
        (4, 7),
        (3, 6),
        (1, 4),
        (2, 5),
        (4, 7),
        (4, 2),
        (6, 4),
        (4, 2),
    ];
    for (a, b) in EXCHANGES {
        let (low, high) = (p[a].min(p[b]), p[a].max(p[b]));
        p[a] = low;
        p[b] = high;
    }
    p[4]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_removes_a_spike() {
        let mut data = vec![3.0f32; 25];
        data[12] = 40.0;
        let out = median3x3(&DisparityImage {
            width: 5,
            height: 5,
            data,
        });
        assert!(out.data.iter().all(|d| *d == 3.0));
    }

    #[test]
    fn the_network_gives_the_sorted_median() {
        let mut state = 11u32;
        for _ in 0..5000 {
            let mut values = [0.0f32; 9];
            for v in &mut values {
                state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                *v = (state >> 20) as f32 / 16.0;
            }
            let mut sorted = values;
            sorted.sort_unstable_by(f32::total_cmp);
            assert_eq!(median_of_nine(&mut values), sorted[4]);
        }
    }
}
