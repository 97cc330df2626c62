//! Lens distortion removed before matching: an image whose calibration has distortion
//! coefficients (`plumb_bob`: k1, k2, p1, p2, k3; `rational_polynomial`: k1, k2, p1, p2, k3, k4,
//! k5, k6) is resampled to the ideal pinhole camera of its K, each output pixel read bilinearly
//! where the distortion model maps it (OpenCV's `initUndistortRectifyMap` with R = I and the new
//! camera matrix K). Zero coefficients leave the image as it is; other models are refused.

use foxglove::messages::CameraCalibration;
use record::camera::PinholeCamera;

/// Largest coefficient still taken as no distortion.
const NEGLIGIBLE: f64 = 1e-12;

/// The image undistorted to `camera` (the pinhole of its K), or why it cannot be.
pub fn undistort(calibration: &CameraCalibration, camera: &PinholeCamera, rgb: &[u8]) -> Result<Vec<u8>, String> {
    let d = &calibration.d;
    if d.iter().all(|c| c.abs() <= NEGLIGIBLE) {
        return Ok(rgb.to_vec());
    }
    let model = calibration.distortion_model.as_str();
    let coefficient = |i: usize| d.get(i).copied().unwrap_or(0.0);
    let (k1, k2, p1, p2, k3) = (
        coefficient(0),
        coefficient(1),
        coefficient(2),
        coefficient(3),
        coefficient(4),
    );
    let (k4, k5, k6) = match model {
        "plumb_bob" | "" if d.len() <= 5 => (0.0, 0.0, 0.0),
        "rational_polynomial" | "plumb_bob" | "" => (coefficient(5), coefficient(6), coefficient(7)),
        other => {
            return Err(format!(
                "'{other}' with coefficients {d:?}: only plumb_bob and rational_polynomial distortion are undistorted (rectify the images first, e.g. with image_proc)"
            ));
        }
    };
    if !d.iter().all(|c| c.is_finite()) {
        return Err(format!("distortion coefficients {d:?} are not finite"));
    }
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut out = vec![0u8; w * h * 3];
    for y in 0..h {
        for x in 0..w {
            let xn = (x as f64 - camera.cx) / camera.fx;
            let yn = (y as f64 - camera.cy) / camera.fy;
            let r2 = xn * xn + yn * yn;
            let radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)));
            let xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn);
            let yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn;
            let (u, v) = (camera.fx * xd + camera.cx, camera.fy * yd + camera.cy);
            let pixel = &mut out[(y * w + x) * 3..(y * w + x) * 3 + 3];
            sample(rgb, w, h, u, v, pixel);
        }
    }
    Ok(out)
}

/// Bilinear sample at (u, v), border replicated; outside the image by more than a pixel: black.
fn sample(rgb: &[u8], w: usize, h: usize, u: f64, v: f64, pixel: &mut [u8]) {
    if !(u > -1.0 && v > -1.0 && u < w as f64 && v < h as f64) {
        return;
    }
    let (u, v) = (u.clamp(0.0, (w - 1) as f64), v.clamp(0.0, (h - 1) as f64));
    let (x0, y0) = (u.floor() as usize, v.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (u - x0 as f64, v - y0 as f64);
    for (c, out) in pixel.iter_mut().enumerate() {
        let at = |x: usize, y: usize| f64::from(rgb[(y * w + x) * 3 + c]);
        let top = at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx;
        let bottom = at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx;
        *out = (top * (1.0 - fy) + bottom * fy).round().clamp(0.0, 255.0) as u8;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn calibration(model: &str, d: Vec<f64>) -> CameraCalibration {
        CameraCalibration {
            distortion_model: model.into(),
            d,
            ..CameraCalibration::default()
        }
    }

    const CAMERA: PinholeCamera = PinholeCamera {
        width: 64,
        height: 48,
        fx: 50.0,
        fy: 50.0,
        cx: 31.5,
        cy: 23.5,
    };

    #[test]
    fn a_distorted_grid_line_comes_out_straight() {
        // A vertical line at x = 50 of an ideal image, drawn where barrel distortion puts it.
        let (k1, w, h) = (-0.2, 64usize, 48usize);
        let mut distorted = vec![0u8; w * h * 3];
        for y in 0..h {
            let (xn, yn) = ((50.0 - CAMERA.cx) / CAMERA.fx, (y as f64 - CAMERA.cy) / CAMERA.fy);
            let r2 = xn * xn + yn * yn;
            let u = CAMERA.fx * xn * (1.0 + k1 * r2) + CAMERA.cx;
            let x = u.round() as usize;
            distorted[(y * w + x) * 3..(y * w + x) * 3 + 3].copy_from_slice(&[255; 3]);
        }
        let out = undistort(
            &calibration("plumb_bob", vec![k1, 0.0, 0.0, 0.0, 0.0]),
            &CAMERA,
            &distorted,
        )
        .unwrap_or_else(|e| panic!("{e}"));
        for y in 4..h - 4 {
            let row = &out[y * w * 3..(y + 1) * w * 3];
            let brightest = (0..w).max_by_key(|x| row[x * 3]).unwrap_or(0);
            assert!(brightest.abs_diff(50) <= 1, "row {y}: the line is at {brightest}");
        }
    }

    #[test]
    fn no_distortion_is_a_copy_and_other_models_are_refused() {
        let rgb: Vec<u8> = (0..64 * 48 * 3).map(|i| (i % 251) as u8).collect();
        assert_eq!(
            undistort(&calibration("plumb_bob", vec![0.0; 5]), &CAMERA, &rgb),
            Ok(rgb.clone())
        );
        let error = undistort(&calibration("equidistant", vec![0.1, 0.0, 0.0, 0.0]), &CAMERA, &rgb).unwrap_err();
        assert!(
            error.contains("'equidistant'") && error.contains("image_proc"),
            "{error}"
        );
    }
}
