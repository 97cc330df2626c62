//! Post-processing of disparity maps.

use crate::image::DisparityImage;

/// 3×3 median of the valid values around each pixel (invalid pixels stay invalid).
pub fn median3x3(input: &DisparityImage) -> DisparityImage {
    let (w, h) = (input.width, input.height);
    let mut data = input.data.clone();
    let mut window = Vec::with_capacity(9);
    for y in 0..h {
        for x in 0..w {
            if !input.data[y * w + x].is_finite() {
                continue;
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
            data[y * w + x] = window[window.len() / 2];
        }
    }
    DisparityImage {
        width: w,
        height: h,
        data,
    }
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
}
