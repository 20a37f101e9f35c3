//! Per-pixel quality flags of a set's products (`products/flags`): which values a reader must
//! not take at face value. Stored as uint8, with the CF attributes `flag_masks` and
//! `flag_meanings`.

use crate::products::Products;

/// Bit 0: a frame of the set saturated at this pixel (every product is NaN there).
pub const SATURATED: u8 = 1;
/// Bit 1: DoLP is undefined (S0 <= 0 after the dark is subtracted).
pub const DOLP_UNDEFINED: u8 = 2;
/// Bit 2: AoP carries no information: undefined (S1 = S2 = 0) or its predicted sigma is
/// above that of an angle drawn uniformly over the half turn, pi / sqrt(12) = 0.907 rad
/// (at DoLP near 0 the first-order sigma grows without bound and means nothing).
pub const AOP_UNDEFINED: u8 = 4;

/// The largest meaningful AoP sigma: the standard deviation of a uniform angle over pi.
pub const AOP_SIGMA_MAX_RAD: f64 = std::f64::consts::PI / 3.464_101_615_137_754_5;

/// The flags of every pixel of `p`.
pub fn pixel_flags(p: &Products) -> Vec<u8> {
    (0..p.pixel_count())
        .map(|i| {
            let mut f = 0u8;
            let all_nan = p.s0[i].is_nan() && p.s1[i].is_nan() && p.s2[i].is_nan();
            if all_nan {
                f |= SATURATED | DOLP_UNDEFINED | AOP_UNDEFINED;
            }
            if !p.dolp[i].is_finite() {
                f |= DOLP_UNDEFINED;
            }
            let sigma = f64::from(p.sigma_aop_rad[i]);
            if !p.aop_rad[i].is_finite() || sigma.is_nan() || sigma > AOP_SIGMA_MAX_RAD {
                f |= AOP_UNDEFINED;
            }
            f
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sigma_limit_is_that_of_a_uniform_half_turn() {
        // Var of U(-pi/2, pi/2) is pi^2 / 12.
        let v = std::f64::consts::PI.powi(2) / 12.0;
        assert!((AOP_SIGMA_MAX_RAD - v.sqrt()).abs() < 1e-15);
    }
}
