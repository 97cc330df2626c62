//! Plain image buffers: 8-bit input views (grey or RGB) and f32 disparity output.

use crate::FuseError;

/// An 8-bit image with 1 (grey) or 3 (RGB) interleaved channels, row-major.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Image {
    /// Width (pixels).
    pub width: usize,
    /// Height (pixels).
    pub height: usize,
    /// Channels per pixel: 1 or 3.
    pub channels: usize,
    /// `width × height × channels` values.
    pub data: Vec<u8>,
}

impl Image {
    /// Wraps a buffer, checking its size.
    pub fn new(width: usize, height: usize, channels: usize, data: Vec<u8>) -> Result<Self, FuseError> {
        if data.len() != width * height * channels || width == 0 || height == 0 || !(channels == 1 || channels == 3) {
            return Err(FuseError::ImageSize {
                what: if channels == 3 { "RGB image" } else { "grey image" },
                width,
                height,
                len: data.len(),
            });
        }
        Ok(Self {
            width,
            height,
            channels,
            data,
        })
    }

    /// A grey image.
    pub fn gray(width: usize, height: usize, data: Vec<u8>) -> Result<Self, FuseError> {
        Self::new(width, height, 1, data)
    }

    /// An RGB image.
    pub fn rgb(width: usize, height: usize, data: Vec<u8>) -> Result<Self, FuseError> {
        Self::new(width, height, 3, data)
    }

    /// Luma (BT.601, rounded) of this image (a copy when already grey).
    pub fn to_gray(&self) -> Self {
        if self.channels == 1 {
            return self.clone();
        }
        let data = self
            .data
            .chunks_exact(3)
            .map(|p| ((299 * u32::from(p[0]) + 587 * u32::from(p[1]) + 114 * u32::from(p[2]) + 500) / 1000) as u8)
            .collect();
        Self {
            width: self.width,
            height: self.height,
            channels: 1,
            data,
        }
    }

    /// Index of the first channel of `(x, y)` with coordinates clamped into the image.
    #[inline]
    pub fn clamped_index(&self, x: isize, y: isize) -> usize {
        let x = x.clamp(0, self.width as isize - 1) as usize;
        let y = y.clamp(0, self.height as isize - 1) as usize;
        (y * self.width + x) * self.channels
    }

    /// Channel `c` at `(x, y)` with coordinates clamped into the image.
    #[inline]
    pub fn clamped(&self, x: isize, y: isize, c: usize) -> u8 {
        self.data[self.clamped_index(x, y) + c]
    }
}

/// Grey levels (BT.601, unrounded) of 8-bit RGB pixels, for the analyses that want floats (the
/// alignment check, the next-best-view planner).
pub fn luma_levels(rgb: &[u8]) -> Vec<f32> {
    rgb.chunks_exact(3)
        .map(|p| 0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1]) + 0.114 * f32::from(p[2]))
        .collect()
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
    /// `width × height` confidences in [0, 1] (1 = certain, 0 = no estimate or a guess), from
    /// each method's own evidence (the cost curve's peak, the network's distribution, graph cuts'
    /// occlusions and label margin), for ranking pixels: every registered method gives them.
    /// `None` where no confidence is known.
    pub confidence: Option<Vec<f32>>,
}

impl DisparityImage {
    /// `Ok` when the map is `width × height` with one value per pixel; else
    /// [`FuseError::ImageSize`] naming `what` the map is for.
    pub fn check_size(&self, width: usize, height: usize, what: &'static str) -> Result<(), FuseError> {
        if self.width != width || self.height != height || self.data.len() != width * height {
            return Err(FuseError::ImageSize {
                what,
                width,
                height,
                len: self.data.len(),
            });
        }
        Ok(())
    }

    /// Fills every invalid pixel with the smaller of the nearest valid disparities to its left
    /// and right on the same row (the background side of an occlusion), as Middlebury's
    /// evaluations of OpenCV and KZ2 do. Rows without any valid pixel stay invalid. A filled
    /// pixel's confidence is 0: it is a guess.
    pub fn fill_invalid_from_row_neighbours(&mut self) {
        let width = self.width;
        if let Some(confidence) = &mut self.confidence {
            for (c, d) in confidence.iter_mut().zip(&self.data) {
                if !d.is_finite() {
                    *c = 0.0;
                }
            }
        }
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

/// A grey test view of a non-repeating texture, its pixel `(x, y)` the texture's `(x + shift, y)`:
/// a fronto-parallel plane at disparity `d` seen from the neighbour at offset `o` along x is
/// `textured_view(w, h, o · d)`, the reference `textured_view(w, h, 0)`.
#[cfg(test)]
pub(crate) fn textured_view(width: usize, height: usize, shift: i64) -> Image {
    let texture = |x: i64, y: i64| (((x * 37 + y * 11) ^ (x * y)) % 97 * 2 + 20) as u8;
    let data = (0..height as i64)
        .flat_map(|y| (0..width as i64).map(move |x| texture(x + shift, y)))
        .collect();
    Image::gray(width, height, data).unwrap_or_else(|e| panic!("{e}"))
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
            confidence: Some(vec![0.5; 6]),
        };
        image.fill_invalid_from_row_neighbours();
        assert_eq!(image.data, vec![5.0, 5.0, 5.0, 5.0, 9.0, 9.0]);
        assert_eq!(image.confidence, Some(vec![0.0, 0.5, 0.0, 0.0, 0.5, 0.0]));
    }

    #[test]
    fn grey_conversion_and_size_checks() {
        let image = Image::rgb(2, 1, vec![255, 255, 255, 0, 0, 255]).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(image.to_gray().data, vec![255, 29]);
        assert!(Image::gray(3, 3, vec![0; 8]).is_err());
        assert!(Image::new(1, 1, 2, vec![0; 2]).is_err());
        assert_eq!(image.clamped(5, -3, 2), 255);
    }
}
