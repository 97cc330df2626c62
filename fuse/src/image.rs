//! Plain image buffers: 8-bit grey input views and f32 disparity output.

use crate::FuseError;

/// An 8-bit single-channel image, row-major.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GrayImage {
    /// Width (pixels).
    pub width: usize,
    /// Height (pixels).
    pub height: usize,
    /// `width × height` values.
    pub data: Vec<u8>,
}

impl GrayImage {
    /// Wraps a buffer, checking its size.
    pub fn new(width: usize, height: usize, data: Vec<u8>) -> Result<Self, FuseError> {
        if data.len() != width * height || width == 0 || height == 0 {
            return Err(FuseError::ImageSize {
                what: "grey image",
                width,
                height,
                len: data.len(),
            });
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// Luma (BT.601, rounded) of an 8-bit RGB buffer.
    pub fn from_rgb(width: usize, height: usize, rgb: &[u8]) -> Result<Self, FuseError> {
        if rgb.len() != width * height * 3 || width == 0 || height == 0 {
            return Err(FuseError::ImageSize {
                what: "RGB image",
                width,
                height,
                len: rgb.len(),
            });
        }
        let data = rgb
            .chunks_exact(3)
            .map(|p| {
                ((299 * u32::from(p[0]) + 587 * u32::from(p[1]) + 114 * u32::from(p[2]) + 500)
                    / 1000) as u8
            })
            .collect();
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// Value at `(x, y)` with coordinates clamped into the image.
    #[inline]
    pub fn clamped(&self, x: isize, y: isize) -> u8 {
        let x = x.clamp(0, self.width as isize - 1) as usize;
        let y = y.clamp(0, self.height as isize - 1) as usize;
        self.data[y * self.width + x]
    }

    /// The image transposed (rows become columns).
    pub fn transposed(&self) -> Self {
        let mut data = vec![0; self.data.len()];
        for y in 0..self.height {
            for x in 0..self.width {
                data[x * self.height + y] = self.data[y * self.width + x];
            }
        }
        Self {
            width: self.height,
            height: self.width,
            data,
        }
    }
}

/// A disparity map in pixels of the reference view; `f32::INFINITY` marks "no estimate"
/// (Middlebury's PFM convention).
#[derive(Debug, Clone, PartialEq)]
pub struct DisparityImage {
    /// Width (pixels).
    pub width: usize,
    /// Height (pixels).
    pub height: usize,
    /// `width × height` disparities.
    pub data: Vec<f32>,
}

impl DisparityImage {
    /// Number of pixels without an estimate.
    pub fn invalid_count(&self) -> usize {
        self.data.iter().filter(|d| !d.is_finite()).count()
    }

    /// Fills every invalid pixel with the smaller of the nearest valid disparities to its left
    /// and right on the same row (the background side of an occlusion), as Middlebury's
    /// evaluations of OpenCV and KZ2 do. Rows without any valid pixel stay invalid.
    pub fn fill_invalid_from_row_neighbours(&mut self) {
        let width = self.width;
        for row in self.data.chunks_mut(width) {
            let mut left = vec![f32::INFINITY; width];
            let mut last = f32::INFINITY;
            for (x, d) in row.iter().enumerate() {
                if d.is_finite() {
                    last = *d;
                }
                left[x] = last;
            }
            let mut next = f32::INFINITY;
            for x in (0..width).rev() {
                if row[x].is_finite() {
                    next = row[x];
                } else {
                    row[x] = match (left[x].is_finite(), next.is_finite()) {
                        (true, true) => left[x].min(next),
                        (true, false) => left[x],
                        (false, true) => next,
                        (false, false) => f32::INFINITY,
                    };
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fill_takes_the_smaller_row_neighbour() {
        let inf = f32::INFINITY;
        let mut image = DisparityImage {
            width: 6,
            height: 1,
            data: vec![inf, 5.0, inf, inf, 9.0, inf],
        };
        image.fill_invalid_from_row_neighbours();
        assert_eq!(image.data, vec![5.0, 5.0, 5.0, 5.0, 9.0, 9.0]);
    }

    #[test]
    fn transpose_twice_is_identity() {
        let image = GrayImage::new(3, 2, vec![1, 2, 3, 4, 5, 6]).unwrap_or_else(|e| panic!("{e}"));
        let t = image.transposed();
        assert_eq!((t.width, t.height), (2, 3));
        assert_eq!(t.data, vec![1, 4, 2, 5, 3, 6]);
        assert_eq!(t.transposed(), image);
        assert!(GrayImage::new(3, 3, vec![0; 8]).is_err());
    }
}
