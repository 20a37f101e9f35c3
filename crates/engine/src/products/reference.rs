//! The plain single-threaded f64 reference of the products, against which the fast path is
//! tested and benchmarked.

use super::error::ProductsError;
use super::geometry::SetGeometry;
use super::inputs::validate;
use super::noise::{Dark, NoiseModel};
use super::planes::Products;

/// The reference implementation: single-threaded, f64 throughout, `f64::atan2` and
/// `f64::sqrt`, the textbook formulas of the module doc (`var AoP` with `L^4`), the same
/// special-pixel rules (with `L == 0` exactly). Used by the tests and the benchmark to check
/// the fast path; results are rounded to f32 at the end.
#[doc(hidden)]
pub fn compute_reference(
    frames: &[&[u16]],
    width: u32,
    height: u32,
    geometry: &SetGeometry,
    dark: &Dark,
    noise: &NoiseModel,
) -> Result<Products, ProductsError> {
    let n = validate(frames, width, height, geometry, dark, noise)?;
    let mut out = Products::empty();
    out.resize(width, height, n);
    let p = &geometry.pinv;
    let k = noise.gain_dn_per_e;
    let sat_dn = noise.saturation_dn;
    for j in 0..n {
        let dk = match dark {
            Dark::Scalar(v) => f64::from(*v),
            Dark::Map(m) => m.get(j).map_or(f64::NAN, |v| f64::from(*v)),
        };
        let mut s = [0.0f64; 3];
        let mut c = [[0.0f64; 3]; 3];
        let mut sat = false;
        for (f, pi) in frames.iter().zip(p) {
            let yv = f.get(j).copied().unwrap_or(0);
            sat |= yv >= sat_dn;
            let y = f64::from(yv);
            let var = k * (y - noise.offset_dn).max(0.0) + noise.read_var_dn2;
            for a in 0..3 {
                s[a] += pi[a] * (y - dk);
                for b in 0..3 {
                    c[a][b] += pi[a] * pi[b] * var;
                }
            }
        }
        let [s0, s1, s2] = s;
        let l = (s1 * s1 + s2 * s2).sqrt();
        let (dolp, sig_p) = if s0 <= 0.0 {
            (f64::NAN, f64::NAN)
        } else if l == 0.0 {
            (0.0, ((c[1][1] + c[2][2]) / 2.0).sqrt() / s0)
        } else {
            let p = l / s0;
            let g = [-p / s0, s1 / (s0 * l), s2 / (s0 * l)];
            let mut v = 0.0;
            for a in 0..3 {
                for b in 0..3 {
                    v += g[a] * c[a][b] * g[b];
                }
            }
            (p, v.max(0.0).sqrt())
        };
        let (aop, sig_a) = if l == 0.0 {
            (f64::NAN, f64::NAN)
        } else {
            let mut aop = 0.5 * s2.atan2(s1);
            if aop <= -std::f64::consts::FRAC_PI_2 {
                aop += std::f64::consts::PI;
            }
            let v = (s1 * s1 * c[2][2] + s2 * s2 * c[1][1] - 2.0 * s1 * s2 * c[1][2])
                / (4.0 * l.powi(4));
            (aop, v.max(0.0).sqrt())
        };
        let o = [
            s0,
            s1,
            s2,
            dolp,
            aop,
            c[0][0].sqrt(),
            c[1][1].sqrt(),
            c[2][2].sqrt(),
            sig_p,
            sig_a,
        ];
        if sat {
            out.saturated += 1;
        }
        for (img, v) in out.images_mut().into_iter().zip(o) {
            if let Some(x) = img.get_mut(j) {
                *x = if sat || !v.is_finite() {
                    f32::NAN
                } else {
                    v as f32
                };
            }
        }
    }
    Ok(out)
}
