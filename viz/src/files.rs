//! Result files other tools open: PFM (Middlebury's float format), 16-bit PNG depth in
//! millimetres, and colour-mapped PNG with the value range in the file name.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use crate::turbo;

/// Errors writing files.
#[derive(Debug, thiserror::Error)]
pub enum FileError {
    /// The file could not be written.
    #[error("cannot write '{path}'")]
    Io {
        /// File.
        path: PathBuf,
        /// Cause.
        #[source]
        source: std::io::Error,
    },
    /// PNG encoding failed.
    #[error("cannot encode '{path}' as PNG: {reason}")]
    Png {
        /// File.
        path: PathBuf,
        /// Cause.
        reason: String,
    },
    /// The buffer does not match the size.
    #[error("'{path}': {len} values for {width}x{height}")]
    Size {
        /// File.
        path: PathBuf,
        /// Values present.
        len: usize,
        /// Width.
        width: usize,
        /// Height.
        height: usize,
    },
}

fn check(path: &Path, len: usize, width: usize, height: usize) -> Result<(), FileError> {
    if len == width * height {
        Ok(())
    } else {
        Err(FileError::Size {
            path: path.to_path_buf(),
            len,
            width,
            height,
        })
    }
}

/// Writes a single-channel PFM (`Pf`, little-endian, rows bottom to top, as Middlebury's tools
/// expect). Invalid values should be `+inf`.
pub fn write_pfm(path: &Path, width: usize, height: usize, data: &[f32]) -> Result<(), FileError> {
    check(path, data.len(), width, height)?;
    let io = |source| FileError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut out = BufWriter::new(File::create(path).map_err(io)?);
    write!(out, "Pf\n{width} {height}\n-1\n").map_err(io)?;
    // A row's bytes at a time, not one `write_all` per value.
    let mut bytes = Vec::with_capacity(width * 4);
    for row in data.chunks_exact(width).rev() {
        bytes.clear();
        bytes.extend(row.iter().flat_map(|v| v.to_le_bytes()));
        out.write_all(&bytes).map_err(io)?;
    }
    out.flush().map_err(io)
}

/// Reads a single-channel PFM written by [`write_pfm`] (either endianness, any row order flag).
pub fn read_pfm(path: &Path) -> Result<(usize, usize, Vec<f32>), FileError> {
    let bytes = std::fs::read(path).map_err(|source| FileError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let bad = |reason: &str| FileError::Io {
        path: path.to_path_buf(),
        source: std::io::Error::new(std::io::ErrorKind::InvalidData, reason.to_owned()),
    };
    let mut fields = Vec::new();
    let mut start = 0;
    let mut header_end = 0;
    for (i, b) in bytes.iter().enumerate() {
        if b.is_ascii_whitespace() {
            if i > start {
                fields.push(String::from_utf8_lossy(&bytes[start..i]).into_owned());
            }
            start = i + 1;
            if fields.len() == 4 {
                header_end = i + 1;
                break;
            }
        }
    }
    if fields.len() < 4 || fields[0] != "Pf" {
        return Err(bad("not a single-channel PFM"));
    }
    let width: usize = fields[1].parse().map_err(|_| bad("bad width"))?;
    let height: usize = fields[2].parse().map_err(|_| bad("bad height"))?;
    let scale: f32 = fields[3].parse().map_err(|_| bad("bad scale"))?;
    let body = &bytes[header_end..];
    let Some(size) = width
        .checked_mul(height)
        .and_then(|n| n.checked_mul(4))
        .filter(|n| *n > 0)
    else {
        return Err(bad("bad width or height"));
    };
    if body.len() < size {
        return Err(bad("truncated data"));
    }
    let mut rows: Vec<Vec<f32>> = body[..size]
        .chunks_exact(width * 4)
        .map(|row| {
            row.chunks_exact(4)
                .map(|b| {
                    let b = [b[0], b[1], b[2], b[3]];
                    if scale < 0.0 {
                        f32::from_le_bytes(b)
                    } else {
                        f32::from_be_bytes(b)
                    }
                })
                .collect()
        })
        .collect();
    rows.reverse();
    Ok((width, height, rows.concat()))
}

fn write_png(
    path: &Path,
    width: usize,
    height: usize,
    color: png::ColorType,
    depth: png::BitDepth,
    data: &[u8],
) -> Result<(), FileError> {
    let io = |source| FileError::Io {
        path: path.to_path_buf(),
        source,
    };
    let png_error = |e: png::EncodingError| FileError::Png {
        path: path.to_path_buf(),
        reason: e.to_string(),
    };
    let file = File::create(path).map_err(io)?;
    let mut encoder = png::Encoder::new(BufWriter::new(file), width as u32, height as u32);
    encoder.set_color(color);
    encoder.set_depth(depth);
    // fdeflate's fast mode: 1080p result images in tens of milliseconds instead of a third of a
    // second each with the default level, for files about 10–30 % larger.
    encoder.set_compression(png::Compression::Fast);
    let mut writer = encoder.write_header().map_err(png_error)?;
    writer.write_image_data(data).map_err(png_error)?;
    writer.finish().map_err(png_error)
}

/// Writes depth (m) as a 16-bit PNG in millimetres (0 = unknown, saturating at 65.535 m).
pub fn write_depth_png_mm(path: &Path, width: usize, height: usize, depth_m: &[f32]) -> Result<(), FileError> {
    check(path, depth_m.len(), width, height)?;
    let mm = depth_m.iter().map(|d| {
        if d.is_finite() && *d > 0.0 {
            (d * 1000.0).round().min(65535.0) as u16
        } else {
            0
        }
    });
    write_gray16(path, width, height, mm)
}

/// Writes values in [0, 1] (a confidence) as a 16-bit grey PNG: 0 → 0, 1 → 65535; NaN → 0.
pub fn write_unit_png16(path: &Path, width: usize, height: usize, values: &[f32]) -> Result<(), FileError> {
    check(path, values.len(), width, height)?;
    let levels = values.iter().map(|v| {
        if v.is_finite() {
            (v.clamp(0.0, 1.0) * 65535.0).round() as u16
        } else {
            0
        }
    });
    write_gray16(path, width, height, levels)
}

/// Writes 16-bit grey levels (row-major, big-endian as PNG stores them).
fn write_gray16(path: &Path, width: usize, height: usize, levels: impl Iterator<Item = u16>) -> Result<(), FileError> {
    let bytes: Vec<u8> = levels.flat_map(u16::to_be_bytes).collect();
    write_png(
        path,
        width,
        height,
        png::ColorType::Grayscale,
        png::BitDepth::Sixteen,
        &bytes,
    )
}

/// Writes 8-bit RGB.
pub fn write_rgb_png(path: &Path, width: usize, height: usize, rgb: &[u8]) -> Result<(), FileError> {
    check(path, rgb.len(), width * 3, height)?;
    write_png(path, width, height, png::ColorType::Rgb, png::BitDepth::Eight, rgb)
}

/// Entries of [`colorize`]'s table: 4096 steps of turbo over [0, 1], finer than its 8-bit
/// channels change (at most one level from the polynomial at the same value).
const TURBO_STEPS: usize = 4096;

/// Colour-maps values with turbo over `[low, high]`; non-finite values are black. Values are
/// looked up in a table of [`TURBO_STEPS`] samples of [`turbo`] (a 1080p image in a few ms
/// instead of a polynomial per pixel).
pub fn colorize(values: &[f32], low: f32, high: f32) -> Vec<u8> {
    static TABLE: std::sync::OnceLock<Vec<[u8; 3]>> = std::sync::OnceLock::new();
    let table = TABLE.get_or_init(|| {
        (0..TURBO_STEPS)
            .map(|i| turbo(i as f64 / (TURBO_STEPS - 1) as f64))
            .collect()
    });
    let span = (high - low).max(f32::EPSILON);
    let scale = (TURBO_STEPS - 1) as f32 / span;
    let mut rgb = vec![0u8; values.len() * 3];
    for (pixel, v) in rgb.chunks_exact_mut(3).zip(values) {
        if v.is_finite() {
            // Clamped, then rounded to the nearest sample (a NaN from a NaN `low` casts to 0).
            let at = ((v - low) * scale).clamp(0.0, (TURBO_STEPS - 1) as f32).round() as usize;
            pixel.copy_from_slice(&table[at]);
        }
    }
    rgb
}

/// The finite range of values (`None` when nothing is finite).
pub fn finite_range(values: &[f32]) -> Option<(f32, f32)> {
    values.iter().filter(|v| v.is_finite()).fold(None, |acc, v| {
        Some(acc.map_or((*v, *v), |(lo, hi): (f32, f32)| (lo.min(*v), hi.max(*v))))
    })
}

/// Writes a colour-mapped PNG named `<stem>_<low>-<high>px.png` in `dir` (the range in the name
/// is the legend) and returns its path.
pub fn write_colormap_png(
    dir: &Path,
    stem: &str,
    width: usize,
    height: usize,
    values: &[f32],
    range: (f32, f32),
) -> Result<PathBuf, FileError> {
    let path = dir.join(format!("{stem}_{:.1}-{:.1}px.png", range.0, range.1));
    let rgb = colorize(values, range.0, range.1);
    write_rgb_png(&path, width, height, &rgb)?;
    Ok(path)
}

/// Intrinsics of the view a disparity map belongs to: `[fx, fy, cx, cy]` (pixels).
pub type Intrinsics = [f64; 4];

/// Points the PLY writer fills its buffer with before each write (15 bytes each: a reused
/// buffer of about 1 MB, cache-resident, instead of a body as large as the file in fresh pages).
const PLY_POINTS_PER_WRITE: usize = 1 << 16;

/// Writes the 3D points of a disparity map as a binary little-endian PLY (`x y z` float metres
/// in the camera's optical frame: x right, y down, z forward; `red green blue` from `rgb`), one
/// vertex per pixel with a finite positive disparity `d = disparity + disparity_offset_px` (the
/// calibration's `doffs`, 0 for our rigs): `z = f·b / d`, `x = (u − cx)·z / fx`,
/// `y = (v − cy)·z / fy`. Returns the number of points written.
pub fn write_ply_points(
    path: &Path,
    (width, height): (usize, usize),
    disparity_px: &[f32],
    disparity_offset_px: f32,
    rgb: &[u8],
    intrinsics: Intrinsics,
    baseline_m: f64,
) -> Result<usize, FileError> {
    check(path, disparity_px.len(), width, height)?;
    check(path, rgb.len(), width * 3, height)?;
    let [fx, fy, cx, cy] = intrinsics;
    let shifted = |d: f32| Some(d + disparity_offset_px).filter(|d| d.is_finite() && *d > 0.0);
    let count = disparity_px.iter().filter(|d| shifted(**d).is_some()).count();
    let header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment multiscopic disparity back-projected in the camera frame (m)\n\
         element vertex {count}\nproperty float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    );
    let io = |source| FileError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut file = File::create(path).map_err(io)?;
    file.write_all(header.as_bytes()).map_err(io)?;
    // x and y as multiples of z: (u − cx) / fx per column, (v − cy) / fy per row.
    let x_per_z: Vec<f64> = (0..width).map(|u| (u as f64 - cx) / fx).collect();
    let mut buffer = Vec::with_capacity(PLY_POINTS_PER_WRITE * 15);
    let rows = disparity_px
        .chunks_exact(width.max(1))
        .zip(rgb.chunks_exact((width * 3).max(1)));
    for (v, (row, colours)) in rows.enumerate() {
        let y_per_z = (v as f64 - cy) / fy;
        for ((d, colour), x_per_z) in row.iter().zip(colours.chunks_exact(3)).zip(&x_per_z) {
            let Some(d) = shifted(*d) else { continue };
            let z = fx * baseline_m / f64::from(d);
            let mut point = [0u8; 15];
            point[0..4].copy_from_slice(&((x_per_z * z) as f32).to_le_bytes());
            point[4..8].copy_from_slice(&((y_per_z * z) as f32).to_le_bytes());
            point[8..12].copy_from_slice(&(z as f32).to_le_bytes());
            point[12..15].copy_from_slice(colour);
            buffer.extend_from_slice(&point);
            if buffer.len() == PLY_POINTS_PER_WRITE * 15 {
                file.write_all(&buffer).map_err(io)?;
                buffer.clear();
            }
        }
    }
    file.write_all(&buffer).map_err(io)?;
    Ok(count)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colorize_is_turbo_within_one_level() {
        let values: Vec<f32> = (0..=20_000).map(|i| -5.0 + i as f32 * 0.0013).collect();
        let (low, high) = (-2.0, 17.0);
        let rgb = colorize(&values, low, high);
        for (v, pixel) in values.iter().zip(rgb.chunks_exact(3)) {
            let want = turbo(f64::from((v - low) / (high - low)));
            for (got, want) in pixel.iter().zip(want) {
                assert!(got.abs_diff(want) <= 1, "{v}: {pixel:?} vs {want}");
            }
        }
        assert_eq!(&rgb[..3], &turbo(0.0), "below the range: its low end");
        assert_eq!(
            colorize(&[f32::NAN, f32::INFINITY, 3.0], 0.0, 3.0),
            [[0, 0, 0], [0, 0, 0], turbo(1.0)].concat()
        );
    }

    #[test]
    fn ply_holds_the_back_projected_plane() {
        // A fronto-parallel plane: constant disparity 10 px, f = 100 px, b = 0.1 m → z = 1 m.
        let dir = std::env::temp_dir().join(format!("viz-ply-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{e}"));
        let path = dir.join("p.ply");
        let mut disparity = vec![10.0f32; 4 * 3];
        disparity[5] = f32::INFINITY;
        let rgb = vec![200u8; 4 * 3 * 3];
        let count = write_ply_points(&path, (4, 3), &disparity, 0.0, &rgb, [100.0, 100.0, 1.5, 1.0], 0.1)
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(count, 11);
        let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{e}"));
        let end = b"end_header\n";
        let start = bytes.windows(end.len()).position(|w| w == end).unwrap_or(0) + end.len();
        assert_eq!(bytes.len() - start, 11 * 15);
        let float = |at: usize| f32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]);
        // First vertex: pixel (0, 0) → x = (0 − 1.5)·1/100, y = (0 − 1)·1/100, z = 1.
        assert!((float(start) + 0.015).abs() < 1e-6 && (float(start + 4) + 0.01).abs() < 1e-6);
        assert!((float(start + 8) - 1.0).abs() < 1e-6);
        // The same plane as disparities of 9 px with a calibration offset of 1 px: the same file.
        let offset = dir.join("offset.ply");
        let nine: Vec<f32> = disparity.iter().map(|d| d - 1.0).collect();
        write_ply_points(&offset, (4, 3), &nine, 1.0, &rgb, [100.0, 100.0, 1.5, 1.0], 0.1)
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(std::fs::read(&offset).unwrap_or_else(|e| panic!("{e}")), bytes);
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn pfm_round_trips_with_infinity() {
        let dir = std::env::temp_dir().join(format!("viz-pfm-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{e}"));
        let path = dir.join("d.pfm");
        let data = vec![1.0, 2.5, f32::INFINITY, 4.0, 5.0, 6.0];
        write_pfm(&path, 3, 2, &data).unwrap_or_else(|e| panic!("{e}"));
        let (w, h, back) = read_pfm(&path).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((w, h), (3, 2));
        assert_eq!(back, data);
        // Rows are stored bottom-up: the file's first float is the last row's first value.
        let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{e}"));
        let header = b"Pf\n3 2\n-1\n".len();
        assert_eq!(
            f32::from_le_bytes([bytes[header], bytes[header + 1], bytes[header + 2], bytes[header + 3]]),
            4.0
        );
        let _ = std::fs::remove_dir_all(dir);
    }
}
