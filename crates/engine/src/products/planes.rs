//! The ten product images of one angle set, and their means.

use super::error::ProductsError;

/// The products of one angle set: ten f32 images, row-major, `width * height` each.
///
/// Reuse one value with [`compute_into`]: its buffers are resized only when the image size
/// changes.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Products {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// S0, DN (dark-subtracted).
    pub s0: Vec<f32>,
    /// S1, DN (`> 0`: horizontal).
    pub s1: Vec<f32>,
    /// S2, DN (`> 0`: +45 deg).
    pub s2: Vec<f32>,
    /// Degree of linear polarisation `sqrt(S1^2 + S2^2) / S0`.
    pub dolp: Vec<f32>,
    /// Angle of polarisation `0.5 atan2(S2, S1)`, radians in `(-pi/2, pi/2)` (module doc).
    pub aop_rad: Vec<f32>,
    /// Predicted standard deviation of S0, DN.
    pub sigma_s0: Vec<f32>,
    /// Predicted standard deviation of S1, DN.
    pub sigma_s1: Vec<f32>,
    /// Predicted standard deviation of S2, DN.
    pub sigma_s2: Vec<f32>,
    /// Predicted (first-order) standard deviation of DoLP.
    pub sigma_dolp: Vec<f32>,
    /// Predicted (first-order) standard deviation of AoP, radians.
    pub sigma_aop_rad: Vec<f32>,
    /// Number of saturated pixels (all outputs NaN).
    pub saturated: u64,
}

/// The image names in storage order.
const NAMES: [&str; 10] = [
    "s0",
    "s1",
    "s2",
    "dolp",
    "aop_rad",
    "sigma_s0",
    "sigma_s1",
    "sigma_s2",
    "sigma_dolp",
    "sigma_aop_rad",
];

/// Means of the product images ([`Products::summary`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProductSummary {
    /// Mean over the finite (and masked-in) pixels of each image, in [`Products::names`]
    /// order; `None` when there is no such pixel.
    pub mean: [Option<f64>; 10],
    /// Number of finite (and masked-in) pixels of each image.
    pub count: [u64; 10],
}

impl ProductSummary {
    /// The mean of the image `name` (see [`Products::names`]).
    pub fn mean_of(&self, name: &str) -> Option<f64> {
        NAMES
            .iter()
            .position(|n| *n == name)
            .and_then(|i| self.mean[i])
    }
}

impl Products {
    /// No pixels.
    pub fn empty() -> Products {
        Products::default()
    }

    /// The image names in storage order: `"s0", "s1", "s2", "dolp", "aop_rad", "sigma_s0",
    /// "sigma_s1", "sigma_s2", "sigma_dolp", "sigma_aop_rad"`.
    pub fn names() -> [&'static str; 10] {
        NAMES
    }

    /// The images in [`Products::names`] order.
    pub fn images(&self) -> [&[f32]; 10] {
        [
            &self.s0,
            &self.s1,
            &self.s2,
            &self.dolp,
            &self.aop_rad,
            &self.sigma_s0,
            &self.sigma_s1,
            &self.sigma_s2,
            &self.sigma_dolp,
            &self.sigma_aop_rad,
        ]
    }

    pub(super) fn images_mut(&mut self) -> [&mut Vec<f32>; 10] {
        [
            &mut self.s0,
            &mut self.s1,
            &mut self.s2,
            &mut self.dolp,
            &mut self.aop_rad,
            &mut self.sigma_s0,
            &mut self.sigma_s1,
            &mut self.sigma_s2,
            &mut self.sigma_dolp,
            &mut self.sigma_aop_rad,
        ]
    }

    /// The image called `name` (one of [`Products::names`]), or `None`.
    pub fn image(&self, name: &str) -> Option<&[f32]> {
        let i = NAMES.iter().position(|n| *n == name)?;
        self.images().get(i).copied()
    }

    /// Number of pixels, `width * height`.
    pub fn pixel_count(&self) -> usize {
        self.s0.len()
    }

    /// The mean of each image over its finite pixels, restricted to the pixels where `mask`
    /// is `true` when a mask is given (one entry per pixel, row-major). Accumulated in f64.
    pub fn summary(&self, mask: Option<&[bool]>) -> Result<ProductSummary, ProductsError> {
        let n = self.pixel_count();
        if let Some(m) = mask {
            if m.len() != n {
                return Err(ProductsError::MaskLength {
                    len: m.len(),
                    expected: n,
                });
            }
        }
        let mut mean = [None; 10];
        let mut count = [0u64; 10];
        for (k, img) in self.images().iter().enumerate() {
            let (mut sum, mut c) = (0.0f64, 0u64);
            for (i, v) in img.iter().enumerate() {
                let keep = mask.is_none_or(|m| m.get(i).copied().unwrap_or(false));
                if keep && v.is_finite() {
                    sum += f64::from(*v);
                    c += 1;
                }
            }
            count[k] = c;
            mean[k] = (c > 0).then(|| sum / c as f64);
        }
        Ok(ProductSummary { mean, count })
    }

    /// Sizes every image for `n` pixels (no reallocation when the size is unchanged).
    pub(super) fn resize(&mut self, width: u32, height: u32, n: usize) {
        self.width = width;
        self.height = height;
        for img in self.images_mut() {
            if img.len() != n {
                img.resize(n, 0.0);
            }
        }
    }
}
