//! A tabulated sky (MODEL.md sections 4 and 10): Stokes radiance on a zenith x azimuth grid that a
//! user exported from a radiative-transfer code (MODTRAN-P, libRadtran, 6SV, ...), read from CSV
//! text and interpolated smoothly over the hemisphere so that it can replace the built-in sky in
//! the skylight integral (Eq. 3.22).
//!
//! # Format
//!
//! ```text
//! # comment lines start with '#'
//! zenith_deg,azimuth_deg,S0,S1,S2
//! 0,0,0.0123,0.0001,-0.0002
//! ...
//! ```
//!
//! * `zenith_deg` in `[0, 90]`, `azimuth_deg` in `[0, 360]`, clockwise from north; the rows must
//!   form a full rectilinear grid (every zenith at every azimuth, any order). The zeniths must
//!   start at 0 and reach at least 80 deg; beyond the last zenith the last row is held. At
//!   least 3 zeniths and 4 azimuths. Azimuth 360, if given, must repeat azimuth 0.
//! * `S0, S1, S2`: band radiance in the user's units (the scene takes W m^-2 sr^-1), `S0 >= 0`,
//!   `S1^2 + S2^2 <= S0^2`.
//! * The Stokes frame of each row is the frame of [`crate::sky`] (`S1 > 0`: the E-vector
//!   horizontal, perpendicular to the vertical plane through the sky point) with
//!   [`StokesReference::Horizontal`]; codes that refer `Q` to the meridian (vertical) plane, as
//!   libRadtran and the Hansen-Travis convention do, use [`StokesReference::Vertical`], which is
//!   that frame turned by 90 deg (`S1` and `S2` change sign).
//!
//! # Interpolation and its error
//!
//! Cubic Hermite (Catmull-Rom) in each direction, periodic in azimuth, one-sided slopes at the
//! zenith ends: continuous with a continuous first derivative, so the adaptive hemisphere
//! integrals converge as they do on the analytic skies. Each component is interpolated in its
//! own row's frame, which turns smoothly with azimuth (at zenith 0, each row is the limit along
//! its own azimuth). [`SkyTable::interpolation_error`] estimates the error from a
//! half-resolution table's error at the points it leaves out, divided by 2 (the least any
//! convergent interpolant gains from halving its step), relative to the peak `S0`. What the
//! grid does not sample it cannot see: a plane-parallel sky's steep rise within a few degrees
//! of the horizon, between the last two zeniths, is the usual blind spot. A 10-degree table of a clear sky interpolates to a few
//! percent near the sun, which no quadrature can improve: the scene measures that floor for
//! each material before integrating, integrates to no less than a quarter of it and adds it to
//! its error ([`crate::scene::ErrorFloor`]).

use crate::polarization::Stokes;
use crate::sky::radiance::SkyRadiance;
use nalgebra::Vector3;

/// Which axis the table's `S1 > 0` refers to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum StokesReference {
    /// `S1 > 0`: E-vector horizontal (this crate's frame).
    #[default]
    Horizontal,
    /// `S1 > 0`: E-vector in the vertical (meridian) plane through the sky point.
    Vertical,
}

/// Errors reading a sky table: each names the line, the column, the value and what is allowed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SkyTableError {
    /// The CSV could not be read.
    #[error("sky table line {line}: {reason}")]
    Csv {
        /// 1-based line number.
        line: u64,
        /// What is wrong.
        reason: String,
    },
    /// The header is not `zenith_deg,azimuth_deg,S0,S1,S2`.
    #[error("sky table header is {found:?}: expected \"zenith_deg,azimuth_deg,S0,S1,S2\"")]
    Header {
        /// The header found.
        found: String,
    },
    /// A value out of range or not a number.
    #[error("sky table line {line}, column {column}: {value:?} is invalid: allowed {allowed}")]
    Value {
        /// 1-based line number.
        line: u64,
        /// Column name.
        column: &'static str,
        /// The text found.
        value: String,
        /// The allowed range.
        allowed: &'static str,
    },
    /// Two rows for one grid point.
    #[error("sky table line {line}: zenith {zenith_deg} deg, azimuth {azimuth_deg} deg repeats line {first_line}")]
    Duplicate {
        /// 1-based line number of the repeat.
        line: u64,
        /// 1-based line number of the first row.
        first_line: u64,
        /// Zenith, degrees.
        zenith_deg: f64,
        /// Azimuth, degrees.
        azimuth_deg: f64,
    },
    /// Grid points without a row.
    #[error("sky table has {count} holes: no row for (zenith_deg, azimuth_deg) {first:?}; every zenith needs every azimuth")]
    Holes {
        /// How many grid points are missing.
        count: usize,
        /// The first few missing points.
        first: Vec<(f64, f64)>,
    },
    /// The grid as a whole is unusable.
    #[error("sky table grid: {0}")]
    Grid(String),
}

/// A sky given on a zenith x azimuth grid, interpolated (module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct SkyTable {
    zenith_deg: Vec<f64>,
    /// Sorted, in `[0, 360)`.
    azimuth_deg: Vec<f64>,
    /// `values[iz * n_az + ia]`, in this crate's frame.
    values: Vec<Vector3<f64>>,
    peak: f64,
    interpolation_error: f64,
}

const COLUMNS: [&str; 5] = ["zenith_deg", "azimuth_deg", "S0", "S1", "S2"];

/// Cubic Hermite weights on `[x1, x2]` with Catmull-Rom slopes from `x0` and `x3`: returns the
/// weights of `y0..y3`. A missing neighbour (`None`) gives a one-sided slope.
fn hermite_weights(x: [Option<f64>; 4], t: f64) -> [f64; 4] {
    let (x1, x2) = (x[1].unwrap_or(0.0), x[2].unwrap_or(1.0));
    let h = x2 - x1;
    let s = ((t - x1) / h).clamp(0.0, 1.0);
    let (s2, s3) = (s * s, s * s * s);
    let h00 = 2.0 * s3 - 3.0 * s2 + 1.0;
    let h10 = s3 - 2.0 * s2 + s;
    let h01 = -2.0 * s3 + 3.0 * s2;
    let h11 = s3 - s2;
    // Slope at x1: (y2 - y0)/(x2 - x0), or (y2 - y1)/h without x0; likewise at x2.
    let mut w = [0.0, h00, h01, 0.0];
    match x[0] {
        Some(x0) => {
            let d = h / (x2 - x0);
            w[0] -= h10 * d;
            w[2] += h10 * d;
        }
        None => {
            w[1] -= h10;
            w[2] += h10;
        }
    }
    match x[3] {
        Some(x3) => {
            let d = h / (x3 - x1);
            w[1] -= h11 * d;
            w[3] += h11 * d;
        }
        None => {
            w[1] -= h11;
            w[2] += h11;
        }
    }
    w
}

impl SkyTable {
    /// Parses and validates CSV text (module docs).
    pub fn from_csv_str(text: &str, reference: StokesReference) -> Result<SkyTable, SkyTableError> {
        let mut reader = csv::ReaderBuilder::new()
            .comment(Some(b'#'))
            .trim(csv::Trim::All)
            .has_headers(true)
            .flexible(true)
            .from_reader(text.as_bytes());
        let header = reader.headers().map_err(|e| SkyTableError::Csv {
            line: e.position().map_or(1, |p| p.line()),
            reason: e.to_string(),
        })?;
        let names: Vec<&str> = header.iter().collect();
        let matches = names.len() == COLUMNS.len()
            && names
                .iter()
                .zip(COLUMNS)
                .all(|(a, b)| a.eq_ignore_ascii_case(b));
        if !matches {
            return Err(SkyTableError::Header {
                found: names.join(","),
            });
        }
        let sign = match reference {
            StokesReference::Horizontal => 1.0,
            StokesReference::Vertical => -1.0,
        };
        // (zenith, azimuth, stokes, line)
        let mut rows: Vec<(f64, f64, Vector3<f64>, u64)> = Vec::new();
        for record in reader.records() {
            let record = record.map_err(|e| SkyTableError::Csv {
                line: e.position().map_or(0, |p| p.line()),
                reason: e.to_string(),
            })?;
            let line = record.position().map_or(0, |p| p.line());
            if record.len() != COLUMNS.len() {
                return Err(SkyTableError::Csv {
                    line,
                    reason: format!(
                        "{} fields, expected 5 ({})",
                        record.len(),
                        COLUMNS.join(",")
                    ),
                });
            }
            let mut v = [0.0; 5];
            for (k, column) in COLUMNS.iter().enumerate() {
                let allowed = match k {
                    0 => "a number in [0, 90]",
                    1 => "a number in [0, 360]",
                    2 => "a finite number >= 0",
                    _ => "a finite number with S1^2 + S2^2 <= S0^2",
                };
                let text = &record[k];
                let bad = || SkyTableError::Value {
                    line,
                    column,
                    value: text.to_string(),
                    allowed,
                };
                let x: f64 = text.parse().map_err(|_| bad())?;
                let ok = x.is_finite()
                    && match k {
                        0 => (0.0..=90.0).contains(&x),
                        1 => (0.0..=360.0).contains(&x),
                        2 => x >= 0.0,
                        _ => true,
                    };
                if !ok {
                    return Err(bad());
                }
                v[k] = x;
            }
            if v[3].hypot(v[4]) > v[2] * (1.0 + 1e-9) + f64::MIN_POSITIVE {
                return Err(SkyTableError::Value {
                    line,
                    column: "S1",
                    value: format!("{}, S2 = {} with S0 = {}", v[3], v[4], v[2]),
                    allowed: "S1^2 + S2^2 <= S0^2 (DoLP <= 1)",
                });
            }
            rows.push((
                v[0],
                v[1],
                Vector3::new(v[2], sign * v[3], sign * v[4]),
                line,
            ));
        }
        if rows.is_empty() {
            return Err(SkyTableError::Grid("no data rows".into()));
        }
        let distinct = |mut xs: Vec<f64>| {
            xs.sort_by(f64::total_cmp);
            xs.dedup();
            xs
        };
        let zenith_deg = distinct(rows.iter().map(|r| r.0).collect());
        let all_az = distinct(rows.iter().map(|r| r.1).collect());
        let has_360 = all_az.last() == Some(&360.0);
        let azimuth_deg: Vec<f64> = all_az.iter().copied().filter(|&a| a < 360.0).collect();
        if zenith_deg[0] != 0.0 {
            return Err(SkyTableError::Grid(format!(
                "the first zenith is {} deg: the table must start at the zenith (0 deg)",
                zenith_deg[0]
            )));
        }
        let last = zenith_deg[zenith_deg.len() - 1];
        if last < 80.0 {
            return Err(SkyTableError::Grid(format!(
                "the last zenith is {last} deg: the table must reach at least 80 deg"
            )));
        }
        if zenith_deg.len() < 3 || azimuth_deg.len() < 4 {
            return Err(SkyTableError::Grid(format!(
                "{} zeniths and {} distinct azimuths: at least 3 and 4 are needed",
                zenith_deg.len(),
                azimuth_deg.len()
            )));
        }
        if has_360 && azimuth_deg[0] != 0.0 {
            return Err(SkyTableError::Grid(
                "azimuth 360 is given without azimuth 0".into(),
            ));
        }
        let (nz, na) = (zenith_deg.len(), azimuth_deg.len());
        let index = |xs: &[f64], x: f64| xs.binary_search_by(|p| p.total_cmp(&x)).ok();
        let mut values: Vec<Option<(Vector3<f64>, u64)>> = vec![None; nz * na];
        let mut wrap: Vec<(usize, Vector3<f64>, u64)> = Vec::new();
        for &(z, a, s, line) in &rows {
            let iz = index(&zenith_deg, z).unwrap_or(0);
            if a == 360.0 {
                wrap.push((iz, s, line));
                continue;
            }
            let k = iz * na + index(&azimuth_deg, a).unwrap_or(0);
            if let Some((_, first_line)) = values[k] {
                return Err(SkyTableError::Duplicate {
                    line,
                    first_line,
                    zenith_deg: z,
                    azimuth_deg: a,
                });
            }
            values[k] = Some((s, line));
        }
        let missing: Vec<(f64, f64)> = values
            .iter()
            .enumerate()
            .filter(|(_, v)| v.is_none())
            .map(|(k, _)| (zenith_deg[k / na], azimuth_deg[k % na]))
            .collect();
        if !missing.is_empty() {
            return Err(SkyTableError::Holes {
                count: missing.len(),
                first: missing.into_iter().take(5).collect(),
            });
        }
        let values: Vec<Vector3<f64>> = values.into_iter().flatten().map(|v| v.0).collect();
        let peak = values.iter().fold(0.0f64, |m, v| m.max(v[0]));
        for (iz, s, line) in wrap {
            let at0 = values[iz * na];
            if (s - at0).norm() > 1e-6 * peak.max(f64::MIN_POSITIVE) {
                return Err(SkyTableError::Value {
                    line,
                    column: "azimuth_deg",
                    value: format!("360 with {:?}", [s[0], s[1], s[2]]),
                    allowed: "azimuth 360 must repeat azimuth 0's row (to 1e-6 of the peak S0)",
                });
            }
        }
        let mut table = SkyTable {
            zenith_deg,
            azimuth_deg,
            values,
            peak,
            interpolation_error: 0.0,
        };
        table.interpolation_error = table.estimate_error();
        Ok(table)
    }

    /// The interpolation error estimate (module docs): a half-resolution table (every other
    /// zenith and azimuth) interpolated at the points it dropped, its largest error divided by
    /// 2 (the least any convergent interpolant gains from halving its step), relative to the
    /// peak `S0`.
    fn estimate_error(&self) -> f64 {
        if self.peak <= 0.0 {
            return 0.0;
        }
        let Some(coarse) = self.half_resolution() else {
            // Too coarse to halve: the bilinear-against-cubic difference at the cell centres.
            return self.linear_difference();
        };
        let (nz, na) = (self.zenith_deg.len(), self.azimuth_deg.len());
        let mut worst = 0.0f64;
        for i in 0..nz {
            for j in 0..na {
                if i % 2 == 0 && j % 2 == 0 {
                    continue;
                }
                let got = coarse.interpolate(self.zenith_deg[i], self.azimuth_deg[j]);
                worst = worst.max((got - self.values[i * na + j]).norm());
            }
        }
        worst / 2.0 / self.peak
    }

    /// The table with every other zenith (and always the last) and every other azimuth, or
    /// `None` when that leaves fewer than 3 zeniths or 4 azimuths. Recomputing a result with
    /// it and halving the change estimates what the interpolation costs that result.
    pub fn half_resolution(&self) -> Option<SkyTable> {
        let (nz, na) = (self.zenith_deg.len(), self.azimuth_deg.len());
        let mut keep_z: Vec<usize> = (0..nz).step_by(2).collect();
        if keep_z.last() != Some(&(nz - 1)) {
            keep_z.push(nz - 1);
        }
        let keep_a: Vec<usize> = (0..na).step_by(2).collect();
        if keep_z.len() < 3 || keep_a.len() < 4 {
            return None;
        }
        Some(SkyTable {
            zenith_deg: keep_z.iter().map(|&i| self.zenith_deg[i]).collect(),
            azimuth_deg: keep_a.iter().map(|&j| self.azimuth_deg[j]).collect(),
            values: keep_z
                .iter()
                .flat_map(|&i| keep_a.iter().map(move |&j| (i, j)))
                .map(|(i, j)| self.values[i * na + j])
                .collect(),
            peak: self.peak,
            interpolation_error: 0.0,
        })
    }

    /// The largest difference between the cubic and the bilinear interpolants at the cell
    /// centres, relative to the peak `S0`.
    fn linear_difference(&self) -> f64 {
        let (nz, na) = (self.zenith_deg.len(), self.azimuth_deg.len());
        let mut worst = 0.0f64;
        for iz in 0..nz - 1 {
            for ia in 0..na {
                let z = 0.5 * (self.zenith_deg[iz] + self.zenith_deg[iz + 1]);
                let a2 = if ia + 1 < na {
                    self.azimuth_deg[ia + 1]
                } else {
                    self.azimuth_deg[0] + 360.0
                };
                let a = 0.5 * (self.azimuth_deg[ia] + a2);
                let cubic = self.interpolate(z, a.rem_euclid(360.0));
                let v = |i: usize, j: usize| self.values[i * na + j % na];
                let linear = (v(iz, ia) + v(iz, ia + 1) + v(iz + 1, ia) + v(iz + 1, ia + 1)) / 4.0;
                worst = worst.max((cubic - linear).norm() / self.peak);
            }
        }
        worst
    }

    /// The interpolated Stokes radiance at a sky point (azimuth clockwise from north).
    fn interpolate(&self, zenith_deg: f64, azimuth_deg: f64) -> Vector3<f64> {
        let (nz, na) = (self.zenith_deg.len(), self.azimuth_deg.len());
        let z = zenith_deg.clamp(0.0, self.zenith_deg[nz - 1]);
        // Zenith cell [iz, iz+1].
        let iz = self
            .zenith_deg
            .partition_point(|&x| x <= z)
            .clamp(1, nz - 1)
            - 1;
        let zx = |k: isize| -> Option<f64> {
            (k >= 0 && (k as usize) < nz).then(|| self.zenith_deg[k as usize])
        };
        let izs = iz as isize;
        let wz = hermite_weights([zx(izs - 1), zx(izs), zx(izs + 1), zx(izs + 2)], z);
        // Azimuth cell, periodic: positions unwrapped around the cell.
        let a = azimuth_deg.rem_euclid(360.0);
        // Left node of the cell, unwrapped: -1 when `a` precedes the first azimuth.
        let left = self.azimuth_deg.partition_point(|&x| x <= a) as isize - 1;
        let ax = |k: isize| -> f64 {
            let m = k.rem_euclid(na as isize);
            self.azimuth_deg[m as usize] + 360.0 * (k - m).div_euclid(na as isize) as f64
        };
        let idx = [left - 1, left, left + 1, left + 2];
        let wa = hermite_weights(idx.map(|k| Some(ax(k))), a);
        let mut out = Vector3::zeros();
        for (dz, &wzk) in wz.iter().enumerate() {
            if wzk == 0.0 {
                continue;
            }
            let kz = izs - 1 + dz as isize;
            if kz < 0 || kz as usize >= nz {
                continue;
            }
            let row = kz as usize * na;
            for (da, &wak) in wa.iter().enumerate() {
                let m = idx[da].rem_euclid(na as isize) as usize;
                out += self.values[row + m] * (wzk * wak);
            }
        }
        out
    }

    /// Stokes radiance from the sky point at `zenith_deg`, `azimuth_deg` (clockwise from north).
    pub fn stokes_at_deg(&self, zenith_deg: f64, azimuth_deg: f64) -> Stokes {
        let mut v = self.interpolate(zenith_deg, azimuth_deg);
        v[0] = v[0].max(0.0);
        Stokes(v)
    }

    /// The interpolation error estimate, relative to the peak `S0` (module docs).
    pub fn interpolation_error(&self) -> f64 {
        self.interpolation_error
    }

    /// The largest tabulated `S0`.
    pub fn peak_radiance(&self) -> f64 {
        self.peak
    }

    /// Grid size: (zeniths, azimuths).
    pub fn grid(&self) -> (usize, usize) {
        (self.zenith_deg.len(), self.azimuth_deg.len())
    }
}

impl SkyRadiance for SkyTable {
    fn stokes_from(&self, towards: &Vector3<f64>) -> Stokes {
        let zenith_deg = towards.z.clamp(-1.0, 1.0).acos().to_degrees().min(90.0);
        let azimuth_deg = towards.x.atan2(towards.y).to_degrees();
        self.stokes_at_deg(zenith_deg, azimuth_deg)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::angles::direction_from_deg;
    use crate::quadrature::Tolerance;
    use crate::sky::RayleighSky;
    use crate::sky::SunlitRayleigh;
    use crate::skylight::sky_irradiance;

    /// A table of `sky` on a `step`-degree grid (zenith 0..=90, azimuth 0..360 or ..=360).
    fn tabulate(sky: &dyn SkyRadiance, dz: f64, da: f64, with_360: bool) -> String {
        let mut out = String::from("# test table\nzenith_deg,azimuth_deg,S0,S1,S2\n");
        let nz = (90.0 / dz).round() as usize;
        let na = (360.0 / da).round() as usize;
        for i in 0..=nz {
            for j in 0..na + usize::from(with_360) {
                let (z, a) = (i as f64 * dz, j as f64 * da);
                // At the zenith, each row is the limit along its own azimuth (module docs).
                let s = sky.stokes_from(&direction_from_deg(z.max(1e-7), a)).0;
                out += &format!("{z},{a},{:e},{:e},{:e}\n", s[0], s[1], s[2]);
            }
        }
        out
    }

    fn rayleigh() -> SunlitRayleigh {
        SunlitRayleigh {
            sky: RayleighSky::at_wavelength(450.0).unwrap(),
            sun: direction_from_deg(46.0, 170.0),
        }
    }

    /// The interpolant reproduces the grid values exactly (1e-12), including across the
    /// azimuth wrap, and is continuous there.
    #[test]
    fn interpolant_is_exact_at_nodes_and_periodic() {
        let sky = rayleigh();
        let t = SkyTable::from_csv_str(
            &tabulate(&sky, 10.0, 10.0, true),
            StokesReference::Horizontal,
        )
        .unwrap();
        assert_eq!(t.grid(), (10, 36));
        for (z, a) in [(0.0f64, 0.0), (30.0, 350.0), (60.0, 0.0), (90.0, 120.0)] {
            let want = sky.stokes_from(&direction_from_deg(z.max(1e-7), a)).0;
            let got = t.stokes_at_deg(z, a).0;
            assert!((got - want).norm() < 1e-12 * t.peak_radiance(), "{z},{a}");
        }
        let left = t.stokes_at_deg(45.0, 359.999_999).0;
        let right = t.stokes_at_deg(45.0, 0.0).0;
        assert!((left - right).norm() < 1e-6 * t.peak_radiance());
    }

    /// Tables of a Rayleigh sky on 10- and 5-degree grids interpolate to within their own error
    /// estimates everywhere above 80 deg zenith (the last cell is the grid's blind spot, module
    /// docs), and the 5-degree table's sky irradiance matches the analytic sky's to 1e-3.
    #[test]
    fn interpolation_error_is_estimated() {
        let sky = rayleigh();
        for step in [10.0, 5.0] {
            let t = SkyTable::from_csv_str(
                &tabulate(&sky, step, step, false),
                StokesReference::Horizontal,
            )
            .unwrap();
            let mut worst = 0.0f64;
            for z in (1..80).step_by(3) {
                for a in (0..360).step_by(7) {
                    let d = direction_from_deg(z as f64 + 0.37, a as f64 + 0.61);
                    let e = (t.stokes_from(&d).0 - sky.stokes_from(&d).0).norm();
                    worst = worst.max(e / t.peak_radiance());
                }
            }
            let estimate = t.interpolation_error();
            assert!(worst <= estimate, "{step}: {worst} vs {estimate}");
            assert!(estimate < 0.1, "{step}: {estimate}");
        }
        let fine = SkyTable::from_csv_str(
            &tabulate(&sky, 5.0, 5.0, false),
            StokesReference::Horizontal,
        )
        .unwrap();
        let exact = sky_irradiance(&sky, Tolerance::absolute(1e-9)).stokes.0[0];
        let table = sky_irradiance(&fine, Tolerance::absolute(1e-9)).stokes.0[0];
        assert!((table - exact).abs() < 1e-3 * exact, "{table} vs {exact}");
    }

    /// The vertical (meridian) reference flips S1 and S2.
    #[test]
    fn vertical_reference_flips_s1_s2() {
        let text = tabulate(&rayleigh(), 10.0, 30.0, false);
        let h = SkyTable::from_csv_str(&text, StokesReference::Horizontal).unwrap();
        let v = SkyTable::from_csv_str(&text, StokesReference::Vertical).unwrap();
        let (a, b) = (h.stokes_at_deg(40.0, 75.0).0, v.stokes_at_deg(40.0, 75.0).0);
        assert_eq!(a[0], b[0]);
        assert!((a[1] + b[1]).abs() < 1e-15 && (a[2] + b[2]).abs() < 1e-15);
    }

    fn err(text: &str) -> String {
        SkyTable::from_csv_str(text, StokesReference::Horizontal)
            .unwrap_err()
            .to_string()
    }

    /// Holes, bad rows and bad grids are errors naming the line, column, value or grid point.
    #[test]
    fn bad_tables_are_errors_naming_the_problem() {
        let good = tabulate(&rayleigh(), 30.0, 90.0, false); // 4 zeniths x 4 azimuths
                                                             // A hole: drop the row for zenith 60, azimuth 90.
        let holed: String = good
            .lines()
            .filter(|l| !l.starts_with("60,90,"))
            .map(|l| format!("{l}\n"))
            .collect();
        let e = err(&holed);
        assert!(e.contains("1 holes") && e.contains("(60.0, 90.0)"), "{e}");
        // A bad number, a negative S0, DoLP > 1, out-of-range zenith, wrong field count.
        let with = |row: &str| format!("{good}{row}\n");
        let e = err(&with("45,10,abc,0,0"));
        assert!(
            e.contains("line 19") && e.contains("S0") && e.contains("abc"),
            "{e}"
        );
        let e = err(&with("45,10,-1,0,0"));
        assert!(e.contains("S0") && e.contains(">= 0"), "{e}");
        let e = err(&with("45,10,1,0.8,0.8"));
        assert!(e.contains("DoLP <= 1"), "{e}");
        let e = err(&with("95,10,1,0,0"));
        assert!(e.contains("zenith_deg") && e.contains("[0, 90]"), "{e}");
        let e = err(&with("45,10,1,0"));
        assert!(e.contains("4 fields"), "{e}");
        let e = err(&with("30,90,1,0,0"));
        assert!(e.contains("repeats line"), "{e}");
        let e = err("zenith,azimuth,I,Q,U\n0,0,1,0,0\n");
        assert!(e.contains("header"), "{e}");
        let e = err("zenith_deg,azimuth_deg,S0,S1,S2\n");
        assert!(e.contains("no data rows"), "{e}");
        let partial: String = good
            .lines()
            .filter(|l| !l.starts_with("90,"))
            .map(|l| format!("{l}\n"))
            .collect();
        assert!(err(&partial).contains("at least 80"), "{}", err(&partial));
        let e = err(&with("0,360,999,0,0"));
        assert!(e.contains("azimuth 360 must repeat azimuth 0"), "{e}");
    }
}
