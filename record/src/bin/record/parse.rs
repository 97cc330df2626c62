//! Value parsers of `record`'s options: each says what it expected.

use record::capture::{CameraAxis, ViewExposure, ViewPoseError};

pub(crate) fn parse_resolution(text: &str) -> Result<(u32, u32), String> {
    let (w, h) = text
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("'{text}' is not WIDTHxHEIGHT, e.g. 1920x1080"))?;
    let side = |s: &str| {
        s.trim()
            .parse::<u32>()
            .ok()
            .filter(|v| (8..=16384).contains(v))
            .ok_or_else(|| format!("'{s}' in '{text}' is not a side length in 8..=16384"))
    };
    Ok((side(w)?, side(h)?))
}

pub(crate) fn parse_positive_mm(text: &str) -> Result<f64, String> {
    let value: f64 = text.parse().map_err(|_| format!("'{text}' is not a number"))?;
    if value > 0.0 && value <= record::capture::MAX_BASELINE_MM {
        Ok(value)
    } else {
        Err(format!(
            "{value} mm is out of range: must be > 0 and ≤ {}",
            record::capture::MAX_BASELINE_MM
        ))
    }
}

pub(crate) fn parse_positive_m(text: &str) -> Result<f64, String> {
    let value: f64 = text.parse().map_err(|_| format!("'{text}' is not a number"))?;
    if value.is_finite() && value > 0.0 {
        Ok(value)
    } else {
        Err(format!("{value} m is out of range: must be a distance > 0"))
    }
}

pub(crate) fn parse_non_negative(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("'{text}' is not a non-negative number")),
    }
}

pub(crate) fn parse_pose_error(text: &str) -> Result<ViewPoseError, String> {
    let parts: Vec<&str> = text.split(':').collect();
    let [role, axis, value] = parts.as_slice() else {
        return Err(format!("'{text}' is not ROLE:AXIS:VALUE, e.g. left:z:0.5"));
    };
    let axis = match axis.to_ascii_lowercase().as_str() {
        "x" => CameraAxis::X,
        "y" => CameraAxis::Y,
        "z" | "roll" => CameraAxis::Z,
        other => return Err(format!("axis '{other}' in '{text}' is not x, y or z")),
    };
    let value: f64 = value
        .parse()
        .ok()
        .filter(|v: &f64| v.is_finite())
        .ok_or_else(|| format!("'{value}' in '{text}' is not a number"))?;
    Ok(ViewPoseError {
        role: (*role).to_owned(),
        axis,
        value,
    })
}

pub(crate) fn parse_exposure(text: &str) -> Result<ViewExposure, String> {
    let (role, gain) = text
        .split_once(':')
        .ok_or_else(|| format!("'{text}' is not ROLE:GAIN, e.g. right:1.2"))?;
    let gain: f64 = gain
        .parse()
        .ok()
        .filter(|g: &f64| g.is_finite() && *g > 0.0)
        .ok_or_else(|| format!("gain '{gain}' in '{text}' is not a positive number"))?;
    Ok(ViewExposure {
        role: role.to_owned(),
        gain,
    })
}

pub(crate) fn parse_triple(text: &str) -> Result<[f64; 3], String> {
    let values: Vec<f64> = text
        .split(',')
        .map(|s| {
            s.trim()
                .parse::<f64>()
                .map_err(|_| format!("'{s}' in '{text}' is not a number"))
        })
        .collect::<Result<_, _>>()?;
    <[f64; 3]>::try_from(values).map_err(|_| format!("'{text}' is not three comma-separated numbers X,Y,Z"))
}
