//! How a store keeps its images: the compression of every image chunk, which product planes
//! are stored (the rest derived on read), and the precision a stored product keeps.
//!
//! * **Compression**: frames, products and the dark mean are compressed with zstd (a core
//!   Zarr v3 codec, level [`ZSTD_LEVEL`]), losslessly.
//! * **Products** ([`ProductSet`]): `essential` (the default) stores S0, DoLP, AoP, the
//!   sigmas of S0 and DoLP, and the flags; S1 and S2 are derived on read
//!   (`S1 = S0 DoLP cos 2 AoP`, `S2 = S0 DoLP sin 2 AoP`, [`derive`]); the sigmas of S1, S2
//!   and AoP come from a recomputation from the stored frames (the frames are lossless).
//!   `all` stores every plane.
//! * **Precision** ([`Precision`]): `sigma` (the default) rounds each stored value to a
//!   multiple of the largest power of two at most half its own pixel's sigma, so the rounding
//!   adds at most `1/sqrt(12) x 1/2 = 0.144` sigma in quadrature, 1.04 % to the pixel's
//!   standard deviation; a sigma plane keeps [`SIGMA_BITS`] significant bits (relative error at
//!   most 2^-5, 3.1 %, well inside what a sigma predicted from noisy signal knows of itself).
//!   Rounded values end in zero bits, which zstd then compresses. `float32` stores the values
//!   as computed.
//!
//! A store written before this existed has no `storage` attribute: it is read and resumed as
//! it was written ([`Storage::legacy`]: uncompressed, every plane, float32).

use super::plane::Plane;
use polar_model::polarization::Stokes;
use serde::{Deserialize, Serialize};

/// The zstd level of every compressed chunk (zstd's own default, the speed and ratio most
/// tools pick).
pub const ZSTD_LEVEL: i32 = 3;

/// Significant bits a stored sigma keeps (besides the implicit leading one).
pub const SIGMA_BITS: u32 = 4;

/// The planes `essential` stores; every other known plane is derived on read.
pub const ESSENTIAL: [&str; 6] = ["s0", "dolp", "aop_rad", "sigma_s0", "sigma_dolp", "flags"];

/// The planes a store can derive on read from the essential ones.
pub const DERIVED: [&str; 2] = ["s1", "s2"];

/// Which product planes a run stores.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "lowercase")]
pub enum ProductSet {
    /// S0, DoLP, AoP, the sigmas of S0 and DoLP, and the flags.
    #[default]
    Essential,
    /// Every plane the kernel computes.
    All,
}

/// The precision a stored product keeps.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// Rounded to what the pixel's sigma warrants (see the module's documentation).
    #[default]
    Sigma,
    /// As computed.
    Float32,
}

/// How a run's store keeps its images: the `storage` root attribute, and a plan's
/// `[storage]` section (every key optional, defaulting to [`Storage::default`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Storage {
    /// `"zstd"` or `"none"`.
    pub compression: Compression,
    /// Which product planes are stored.
    pub products: ProductSet,
    /// The precision a stored product keeps.
    pub precision: Precision,
}

/// The compression of every image chunk.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum Compression {
    /// zstd at [`ZSTD_LEVEL`].
    Zstd,
    /// Uncompressed (stores written before compression existed).
    None,
}

impl Default for Storage {
    fn default() -> Self {
        Storage {
            compression: Compression::Zstd,
            products: ProductSet::Essential,
            precision: Precision::Sigma,
        }
    }
}

impl Storage {
    /// A store written before the `storage` attribute existed.
    pub fn legacy() -> Storage {
        Storage {
            compression: Compression::None,
            products: ProductSet::All,
            precision: Precision::Float32,
        }
    }

    /// Whether image chunks are zstd-compressed.
    pub fn compressed(&self) -> bool {
        self.compression == Compression::Zstd
    }

    /// Whether plane `name` is stored (names outside the kernel's are always stored).
    pub fn keeps(&self, name: &str) -> bool {
        self.products == ProductSet::All || ESSENTIAL.contains(&name) || !is_kernel_plane(name)
    }

    /// The sigma plane whose pixel-wise value sets the rounding step of value plane `name`.
    pub fn sigma_of(name: &str) -> Option<&'static str> {
        match name {
            "s0" => Some("sigma_s0"),
            "s1" => Some("sigma_s1"),
            "s2" => Some("sigma_s2"),
            "dolp" => Some("sigma_dolp"),
            "aop_rad" => Some("sigma_aop_rad"),
            _ => None,
        }
    }

    /// The attribute a stored plane carries to say how it was rounded (`None`: as computed).
    pub fn rounding_note(&self, name: &str) -> Option<String> {
        if self.precision != Precision::Sigma {
            return None;
        }
        if let Some(sigma) = Self::sigma_of(name) {
            Some(format!(
                "rounded to a multiple of the largest power of two at most half the pixel's \
                 {sigma} (adds at most 1.04 % to its standard deviation)"
            ))
        } else if name.starts_with("sigma_") {
            Some(format!(
                "rounded to {SIGMA_BITS} significant bits after the leading one (relative \
                 error at most 2^-{})",
                SIGMA_BITS + 1
            ))
        } else {
            None
        }
    }
}

/// A plane as it will be stored: the caller's, or a rounded copy.
#[derive(Debug)]
pub enum Kept<'a> {
    /// Stored as given.
    Same(Plane<'a>),
    /// Rounded to its precision.
    Rounded(Vec<f32>),
}

impl Kept<'_> {
    /// The plane to store.
    pub fn plane(&self) -> Plane<'_> {
        match self {
            Kept::Same(p) => *p,
            Kept::Rounded(v) => Plane::F32(v),
        }
    }
}

impl Storage {
    /// The planes of `images` this store keeps, each rounded to its precision (a value plane
    /// by its own sigma plane, which must be among `images` to be rounded, stored or not).
    pub fn prepare<'a>(&self, images: &[(&'a str, Plane<'a>)]) -> Vec<(&'a str, Kept<'a>)> {
        let find = |name: &str| {
            images.iter().find_map(|(n, p)| match p {
                Plane::F32(v) if *n == name => Some(*v),
                _ => None,
            })
        };
        let sigma_rounding = self.precision == Precision::Sigma;
        images
            .iter()
            .filter(|(n, _)| self.keeps(n))
            .map(|(n, p)| {
                let kept = match p {
                    Plane::F32(v) if sigma_rounding => match Self::sigma_of(n).and_then(&find) {
                        Some(sigma) => Kept::Rounded(
                            v.iter()
                                .zip(sigma)
                                .map(|(&x, &s)| round_to_sigma(x, s))
                                .collect(),
                        ),
                        None if n.starts_with("sigma_") && is_kernel_plane(n) => {
                            Kept::Rounded(v.iter().map(|&x| round_sigma(x)).collect())
                        }
                        None => Kept::Same(*p),
                    },
                    _ => Kept::Same(*p),
                };
                (*n, kept)
            })
            .collect()
    }
}

fn is_kernel_plane(name: &str) -> bool {
    crate::products::Products::names().contains(&name) || name == "flags"
}

/// Rounds `v` to a multiple of the largest power of two at most `sigma / 2` (unchanged where
/// either is not finite or `sigma` is not positive).
pub fn round_to_sigma(v: f32, sigma: f32) -> f32 {
    if !(v.is_finite() && sigma.is_finite() && sigma > 0.0) {
        return v;
    }
    let step = pow2_at_most(sigma * 0.5);
    if step == 0.0 || !step.is_finite() {
        return v;
    }
    (v / step).round_ties_even() * step
}

/// The largest power of two at most `x` (`x` positive and finite; 0 when `x` is below the
/// smallest normal float32).
fn pow2_at_most(x: f32) -> f32 {
    if x < f32::MIN_POSITIVE {
        return 0.0;
    }
    f32::from_bits(x.to_bits() & 0xff80_0000)
}

/// Rounds `v` to [`SIGMA_BITS`] significant bits after the leading one (to nearest, ties to
/// even; non-finite values unchanged).
pub fn round_sigma(v: f32) -> f32 {
    if !v.is_finite() {
        return v;
    }
    let drop = 23 - SIGMA_BITS;
    let bits = v.to_bits();
    let half = 1u32 << (drop - 1);
    let keep_lsb = (bits >> drop) & 1;
    let rounded = bits.wrapping_add(half - 1 + keep_lsb) & !((1u32 << drop) - 1);
    let out = f32::from_bits(rounded);
    if out.is_finite() {
        out
    } else {
        v
    }
}

/// Derives plane `name` (one of [`DERIVED`]) from S0, DoLP and AoP, pixel by pixel: the
/// polarised part `S0 DoLP` at AoP as the model's [`Stokes::linear`] writes it.
pub fn derive(name: &str, s0: &[f32], dolp: &[f32], aop: &[f32]) -> Option<Vec<f32>> {
    let component = match name {
        "s1" => 1,
        "s2" => 2,
        _ => return None,
    };
    Some(
        s0.iter()
            .zip(dolp)
            .zip(aop)
            .map(|((&s, &p), &a)| {
                let polarised = Stokes::linear(f64::from(s) * f64::from(p), f64::from(a));
                polarised.0[component] as f32
            })
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sigma_rounding_stays_within_a_quarter_sigma() {
        // The step is a power of two in (sigma/4, sigma/2], so the error is at most sigma/4.
        for &(v, s) in &[
            (0.337f32, 0.01f32),
            (1234.5, 3.7),
            (-0.9, 0.2),
            (2.0e4, 150.0),
        ] {
            let r = round_to_sigma(v, s);
            assert!((r - v).abs() <= s / 4.0, "{v} {s} -> {r}");
            let step = pow2_at_most(s / 2.0);
            assert!(step > s / 4.0 && step <= s / 2.0, "{s}: step {step}");
            assert_eq!((r / step).fract(), 0.0, "{r} is a multiple of {step}");
        }
        assert!(round_to_sigma(f32::NAN, 1.0).is_nan());
        assert_eq!(round_to_sigma(0.3, f32::NAN), 0.3);
        assert_eq!(round_to_sigma(0.3, 0.0), 0.3);
    }

    #[test]
    fn sigma_planes_keep_their_bits() {
        // Relative error at most 2^-(SIGMA_BITS + 1), and the dropped bits are zero.
        for &v in &[0.0123f32, 1.0, 3.999, 77.7, 1.0e-7] {
            let r = round_sigma(v);
            assert!(
                ((r - v) / v).abs() <= 2f32.powi(-(SIGMA_BITS as i32 + 1)),
                "{v} -> {r}"
            );
            assert_eq!(r.to_bits() & ((1 << (23 - SIGMA_BITS)) - 1), 0);
        }
        assert_eq!(round_sigma(f32::INFINITY), f32::INFINITY);
        assert_eq!(
            round_sigma(f32::MAX),
            f32::MAX,
            "rounding up past MAX keeps the value"
        );
    }

    #[test]
    fn derived_stokes_invert_dolp_and_aop() {
        // S1 = S0 p cos 2a and S2 = S0 p sin 2a: a pixel at a = 30 deg, p = 0.5, S0 = 100.
        let a = 30f32.to_radians();
        let s1 = derive("s1", &[100.0], &[0.5], &[a]).unwrap();
        let s2 = derive("s2", &[100.0], &[0.5], &[a]).unwrap();
        assert!((s1[0] - 25.0).abs() < 1e-4 && (s2[0] - 43.30127).abs() < 1e-4);
        assert!(derive("dolp", &[1.0], &[1.0], &[1.0]).is_none());
    }
}
