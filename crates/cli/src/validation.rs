//! `polarimeter report validation`: the analytic DoLP and AoP statistics against a seeded,
//! parallel Monte Carlo of the whole sensor chain ([`polar_model::validation`]) over a grid of
//! scene states, analyzer angle sets and noise levels (the two example cameras at several
//! exposure times), written as a Markdown report (docs/VALIDATION.md).

use polar_model::atmosphere::Band;
use polar_model::polarization::Stokes;
use polar_model::sensor::{Camera, Exposure, SensorModel};
use polar_model::stats::{dolp_aop_stats, RegimeChoice, StatsMethod, RICE_SNR_THRESHOLD};
use polar_model::validation::{self, Agreement, Comparison, McConfig, McSource, ValidationPoint};
use polar_model::ModelError;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// The command that regenerates the accuracy-grid report, docs/validation/dolp-aop-grid.md
/// (linked from docs/VALIDATION.md).
pub const GRID_COMMAND: &str =
    "polarimeter bench stats --grid --grid-samples 4000000 --seed 1 --out docs/validation/dolp-aop-grid.md";

/// The example cameras, embedded so that the report runs from any directory: a short label,
/// the file name and its text.
pub const CAMERAS: [(&str, &str, &str); 2] = [
    (
        "CCD",
        "examples/cameras/ccd_seed.toml",
        include_str!("../../../examples/cameras/ccd_seed.toml"),
    ),
    (
        "CMOS",
        "examples/cameras/cmos_modern.toml",
        include_str!("../../../examples/cameras/cmos_modern.toml"),
    ),
];

/// Most frame sets per grid point accepted by [`run`].
pub const MAX_SETS_PER_POINT: usize = 10_000_000;

/// Errors of the validation report.
#[derive(Debug, thiserror::Error)]
pub enum ValidationError {
    /// The model refused an input.
    #[error(transparent)]
    Model(#[from] ModelError),
    /// The report could not be written.
    #[error("{path}: cannot write: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// An option out of its range.
    #[error("{0}")]
    Invalid(String),
}

/// How bright a noise level is: mean photo-electrons per frame of an unpolarised scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Level {
    /// Read-noise limited: `max(sigma_d^2, 20)` electrons (shot variance equal to the read
    /// variance, at least 20 e- so that `S0_hat > 0` in every set).
    ReadLimited,
    /// This fraction of the full well.
    FullWellFraction(f64),
}

impl Level {
    fn electrons(&self, cam: &Camera) -> f64 {
        match *self {
            Level::ReadLimited => (cam.read_noise_e * cam.read_noise_e).max(20.0),
            Level::FullWellFraction(f) => f * cam.full_well_e,
        }
    }

    fn label(&self) -> String {
        match *self {
            Level::ReadLimited => "read-limited".into(),
            Level::FullWellFraction(f) => format!("{:.0} % FW", f * 100.0),
        }
    }
}

/// The grid of the report.
#[derive(Debug, Clone, PartialEq)]
pub struct GridSpec {
    /// Cameras: label and camera.
    pub cameras: Vec<(String, Camera)>,
    /// Flat band, nm.
    pub band_nm: (f64, f64),
    /// Scene `S0`, W m^-2 sr^-1 (the exposure time sets the electrons).
    pub s0_w_m2_sr: f64,
    /// Noise levels (exposure times follow from them).
    pub levels: Vec<Level>,
    /// Analyzer angle sets, degrees.
    pub angle_sets_deg: Vec<Vec<f64>>,
    /// Scene DoLPs; DoLP 0 is taken once (no AoP).
    pub dolps: Vec<f64>,
    /// Scene AoPs, degrees.
    pub aops_deg: Vec<f64>,
}

impl GridSpec {
    /// The report's grid: both example cameras through a flat 500-600 nm band, a scene of
    /// `S0 = 0.1 W m^-2 sr^-1` (dim daylight), three noise levels (read-noise limited, 5 % and
    /// 45 % of the full well, the brightest frame of a DoLP 0.9 scene then at 85 %), angle sets
    /// 0/60/120, 0/45/90, 0/45/90/135 and six equally spaced, DoLP 0, 0.02, 0.1, 0.3, 0.9 at
    /// AoP 15 and 60 deg: 216 points.
    pub fn report() -> Result<GridSpec, ValidationError> {
        let mut cameras = Vec::new();
        for (label, _, text) in CAMERAS {
            cameras.push((label.to_string(), Camera::from_toml_str(text)?));
        }
        Ok(GridSpec {
            cameras,
            band_nm: (500.0, 600.0),
            s0_w_m2_sr: 0.1,
            levels: vec![
                Level::ReadLimited,
                Level::FullWellFraction(0.05),
                Level::FullWellFraction(0.45),
            ],
            angle_sets_deg: vec![
                vec![0.0, 60.0, 120.0],
                vec![0.0, 45.0, 90.0],
                vec![0.0, 45.0, 90.0, 135.0],
                vec![0.0, 30.0, 60.0, 90.0, 120.0, 150.0],
            ],
            dolps: vec![0.0, 0.02, 0.1, 0.3, 0.9],
            aops_deg: vec![15.0, 60.0],
        })
    }

    /// The grid's points, in a fixed order (camera, level, angle set, DoLP, AoP).
    pub fn points(&self) -> Result<Vec<GridPoint>, ValidationError> {
        let band = Band::flat(self.band_nm.0, self.band_nm.1)?;
        let mut out = Vec::new();
        for (label, cam) in &self.cameras {
            let model = SensorModel::new(cam, &band)?;
            for level in &self.levels {
                let electrons = level.electrons(cam);
                for angles_deg in &self.angle_sets_deg {
                    let angles: Vec<f64> = angles_deg.iter().map(|d| d.to_radians()).collect();
                    let w = model.intensities_from_stokes(&angles)?;
                    let w0 = w.column(0).mean();
                    let per_s = model.responsivity_e_per_s() * w0 * self.s0_w_m2_sr;
                    if !(per_s.is_finite() && per_s > 0.0) {
                        return Err(ValidationError::Invalid(format!(
                            "camera {label}: no signal in the band {:?} nm",
                            self.band_nm
                        )));
                    }
                    let t_int_s = electrons / per_s;
                    let mut states = Vec::new();
                    for &dolp in &self.dolps {
                        if dolp == 0.0 {
                            states.push((0.0, 0.0));
                        } else {
                            states.extend(self.aops_deg.iter().map(|&a| (dolp, a)));
                        }
                    }
                    for (dolp, aop_deg) in states {
                        let two_a = 2.0 * f64::to_radians(aop_deg);
                        let s0 = self.s0_w_m2_sr;
                        let stokes =
                            Stokes::new(s0, s0 * dolp * two_a.cos(), s0 * dolp * two_a.sin());
                        out.push(GridPoint {
                            camera: label.clone(),
                            model: model.clone(),
                            angles_deg: angles_deg.clone(),
                            level: level.label(),
                            mean_electrons: electrons,
                            dolp,
                            aop_deg,
                            exposure: Exposure::new(t_int_s, stokes),
                        });
                    }
                }
            }
        }
        Ok(out)
    }
}

/// One point of the grid.
#[derive(Debug, Clone, PartialEq)]
pub struct GridPoint {
    /// Camera label.
    pub camera: String,
    /// The camera through the band.
    pub model: SensorModel,
    /// Analyzer angles, degrees.
    pub angles_deg: Vec<f64>,
    /// Noise level label.
    pub level: String,
    /// Mean photo-electrons per frame of the unpolarised part.
    pub mean_electrons: f64,
    /// Scene DoLP.
    pub dolp: f64,
    /// Scene AoP, degrees.
    pub aop_deg: f64,
    /// The exposure (time and scene radiance).
    pub exposure: Exposure,
}

impl GridPoint {
    fn angles_rad(&self) -> Vec<f64> {
        self.angles_deg.iter().map(|d| d.to_radians()).collect()
    }

    fn angles_label(&self) -> String {
        if self.angles_deg.len() == 6 {
            "6 x 30".into()
        } else {
            self.angles_deg
                .iter()
                .map(|a| format!("{a:.0}"))
                .collect::<Vec<_>>()
                .join("/")
        }
    }
}

/// One row of the report: the point, the analytic method's validation, the Taylor and Rice
/// approximations against the same Monte Carlo, and a Gaussian Stokes-level Monte Carlo.
#[derive(Debug, Clone, PartialEq)]
pub struct Row {
    /// The grid point.
    pub point: GridPoint,
    /// Analytic ([`RegimeChoice::Auto`]: the integration at every polarised SNR) against the
    /// whole-chain Monte Carlo.
    pub result: ValidationPoint,
    /// The delta-method ("Taylor") approximation against the same Monte Carlo; `None` at
    /// `p = 0`, where its forms are singular.
    pub taylor: Option<Comparison>,
    /// The isotropic Rice approximation against the same Monte Carlo.
    pub rice: Comparison,
    /// A Gaussian Monte Carlo at the Stokes level with the same mean and covariance, to tell
    /// the analytic method's error from the chain's departure from Gaussian Stokes noise.
    pub gauss: GaussCheck,
}

/// Differences, in Monte Carlo standard errors, between the analytic values, a Gaussian
/// Stokes-level Monte Carlo ([`McSource::GaussianStokes`]: the analytic Stokes mean and
/// covariance, as many draws, the same statistics) and the whole-chain Monte Carlo, per
/// statistic `[DoLP mean, DoLP std, AoP std]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GaussCheck {
    /// `(analytic - Gaussian MC) / SE_gauss`: the error of the analytic method alone.
    pub formulas_z: [f64; 3],
    /// `(Gaussian MC - chain MC) / sqrt(SE_gauss^2 + SE_chain^2)`: the chain's departure from
    /// Gaussian Stokes noise (Poisson counts, rounding to whole DN).
    pub chain_z: [f64; 3],
    /// The Gaussian Monte Carlo's values.
    pub values: [f64; 3],
}

/// The seed of point `index` of a run seeded `seed`.
fn point_seed(seed: u64, index: usize) -> u64 {
    seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (index as u64).wrapping_add(1)
}

/// Runs every point with `sets` frame sets (seeded per point from `seed`), all available
/// threads. Errors: `sets` outside `2 ..= MAX_SETS_PER_POINT`; the model's.
pub fn run(points: &[GridPoint], sets: usize, seed: u64) -> Result<Vec<Row>, ValidationError> {
    if !(2..=MAX_SETS_PER_POINT).contains(&sets) {
        return Err(ValidationError::Invalid(format!(
            "sets = {sets} is out of range: allowed 2 to {MAX_SETS_PER_POINT}"
        )));
    }
    let mut rows = Vec::with_capacity(points.len());
    for (i, point) in points.iter().enumerate() {
        let cfg = McConfig::new(sets, point_seed(seed, i));
        let result = validation::validate_point(
            &point.model,
            &point.angles_rad(),
            &point.exposure,
            RegimeChoice::Auto,
            &cfg,
        )?;
        let a = &result.analytic;
        let (mean, cov) = (&a.stokes_mean_w_m2_sr, &a.estimator.cov);
        let taylor = dolp_aop_stats(mean, cov, RegimeChoice::Taylor)?;
        let taylor = (taylor.method == StatsMethod::Taylor)
            .then(|| validation::compare(&taylor, cov, &result.monte_carlo));
        let rice = dolp_aop_stats(mean, cov, RegimeChoice::Rice)?;
        let rice = validation::compare(&rice, cov, &result.monte_carlo);
        let gauss_cfg = McConfig {
            source: McSource::GaussianStokes,
            seed: point_seed(seed ^ 0x6761_7573_7369_616e, i),
            ..cfg
        };
        let g = validation::simulate_products(
            &point.model,
            &point.angles_rad(),
            &point.exposure,
            &gauss_cfg,
        )?;
        let c = &result.comparison;
        let an = [
            c.dolp_mean.analytic,
            c.dolp_std.analytic,
            c.aop_std.analytic,
        ];
        let mc = [
            c.dolp_mean.monte_carlo,
            c.dolp_std.monte_carlo,
            c.aop_std.monte_carlo,
        ];
        let se = [c.dolp_mean.se, c.dolp_std.se, c.aop_std.se];
        let ga = [g.dolp_mean, g.dolp_std, g.aop_std_rad];
        let ga_se = [g.dolp_mean_se, g.dolp_std_se, g.aop_std_se_rad];
        let z = |d: f64, s: f64| if s > 0.0 { d / s } else { 0.0 };
        let gauss = GaussCheck {
            formulas_z: std::array::from_fn(|k| z(an[k] - ga[k], ga_se[k])),
            chain_z: std::array::from_fn(|k| z(ga[k] - mc[k], ga_se[k].hypot(se[k]))),
            values: ga,
        };
        rows.push(Row {
            point: point.clone(),
            result,
            taylor,
            rice,
            gauss,
        });
    }
    Ok(rows)
}

/// Summary of one statistic over a group of rows.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StatSummary {
    /// Largest `|relative error|`.
    pub max_rel: f64,
    /// Median `|relative error|`.
    pub median_rel: f64,
    /// Largest `|z|` (difference in Monte Carlo standard errors).
    pub max_z: f64,
    /// Fraction of rows with `|z| < 4`.
    pub within_4se: f64,
}

/// Summary of a group of comparisons.
#[derive(Debug, Clone, PartialEq)]
pub struct GroupSummary {
    /// What the group is.
    pub label: String,
    /// Rows in it.
    pub count: usize,
    /// DoLP mean.
    pub dolp_mean: StatSummary,
    /// DoLP standard deviation.
    pub dolp_std: StatSummary,
    /// AoP standard deviation.
    pub aop_std: StatSummary,
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

fn stat_summary(agreements: &[Agreement]) -> StatSummary {
    let rel: Vec<f64> = agreements.iter().map(|a| a.rel_error.abs()).collect();
    let z: Vec<f64> = agreements.iter().map(|a| a.z.abs()).collect();
    StatSummary {
        max_rel: rel.iter().copied().fold(0.0, f64::max),
        median_rel: median(rel),
        max_z: z.iter().copied().fold(0.0, f64::max),
        within_4se: z.iter().filter(|&&z| z < 4.0).count() as f64 / z.len().max(1) as f64,
    }
}

/// Summarises `comparisons` under `label`; `None` when empty.
pub fn summarise(label: &str, comparisons: &[&Comparison]) -> Option<GroupSummary> {
    if comparisons.is_empty() {
        return None;
    }
    let pick = |f: fn(&Comparison) -> Agreement| -> Vec<Agreement> {
        comparisons.iter().map(|c| f(c)).collect()
    };
    Some(GroupSummary {
        label: label.to_string(),
        count: comparisons.len(),
        dolp_mean: stat_summary(&pick(|c| c.dolp_mean)),
        dolp_std: stat_summary(&pick(|c| c.dolp_std)),
        aop_std: stat_summary(&pick(|c| c.aop_std)),
    })
}

/// Whether the `(S1, S2)` block of the Stokes covariance is anisotropic (eigenvalues differing
/// by more than 5 %, the threshold at which the Rice approximation warns).
pub fn anisotropic(row: &Row) -> bool {
    let c = &row.result.analytic.estimator.cov;
    let (a, b, d) = (c[(1, 1)], c[(1, 2)], c[(2, 2)]);
    let mean = 0.5 * (a + d);
    let half_gap = (0.25 * (a - d) * (a - d) + b * b).sqrt();
    let (hi, lo) = (mean + half_gap, mean - half_gap);
    hi > 0.0 && hi - lo > 0.05 * hi
}

/// `S0 / sigma_S0` of the Stokes estimate: how well the DoLP's denominator is known.
pub fn s0_snr(row: &Row) -> f64 {
    let a = &row.result.analytic;
    a.stokes_mean_w_m2_sr[0] / a.estimator.cov[(0, 0)].max(0.0).sqrt()
}

/// `S0 / sigma_S0` below which a point counts as having a noisy denominator: the Rice
/// approximation's first-order treatment of the `S0` noise misses `3 (sigma_S0/S0)^2` of the
/// DoLP variance, 0.75 % at 20.
pub const S0_SNR_LOW: f64 = 20.0;

/// Polarised-SNR bands of the summary, `[lo, hi)`, the lowest ending at
/// [`RICE_SNR_THRESHOLD`] (where the Taylor approximation stops applying).
pub const SNR_BANDS: [(f64, f64); 4] = [
    (10.0, f64::INFINITY),
    (5.0, 10.0),
    (RICE_SNR_THRESHOLD, 5.0),
    (0.0, RICE_SNR_THRESHOLD),
];

fn band_label((lo, hi): (f64, f64)) -> String {
    if hi.is_infinite() {
        format!("SNR_p >= {lo}")
    } else if lo == 0.0 {
        format!("SNR_p < {hi}")
    } else {
        format!("{lo} <= SNR_p < {hi}")
    }
}

fn in_band(r: &Row, (lo, hi): (f64, f64)) -> bool {
    let s = r.result.comparison.polarised_snr;
    s >= lo && s < hi
}

/// A group of rows for the summary: its label and which rows (with the comparison to use).
type Group<'a> = (String, Vec<(&'a Row, &'a Comparison)>);

/// The analytic method's groups: all points; each polarised-SNR band split by isotropy of the
/// `(S1, S2)` noise; the read-noise-limited points (`S0 / sigma_S0 < S0_SNR_LOW`).
fn group_rows(rows: &[Row]) -> Vec<Group<'_>> {
    let pick = |f: &dyn Fn(&Row) -> bool| -> Vec<(&Row, &Comparison)> {
        rows.iter()
            .filter(|r| f(r))
            .map(|r| (r, &r.result.comparison))
            .collect()
    };
    let mut out = vec![("all points".to_string(), pick(&|_| true))];
    for band in SNR_BANDS {
        for (iso, name) in [(true, "isotropic"), (false, "anisotropic")] {
            out.push((
                format!("{}, {name} (S1, S2) noise", band_label(band)),
                pick(&|r| in_band(r, band) && anisotropic(r) != iso),
            ));
        }
    }
    out.push((
        format!("S0 SNR < {S0_SNR_LOW} (read-noise limited), any SNR_p"),
        pick(&|r| s0_snr(r) < S0_SNR_LOW),
    ));
    out
}

/// The approximations' groups: the Taylor approximation per polarised-SNR band (none at
/// `p = 0`); the Rice approximation per band on isotropic noise, and on anisotropic noise.
fn approx_group_rows(rows: &[Row]) -> Vec<Group<'_>> {
    let mut out = Vec::new();
    for band in SNR_BANDS {
        out.push((
            format!("Taylor, {}", band_label(band)),
            rows.iter()
                .filter(|r| in_band(r, band))
                .filter_map(|r| r.taylor.as_ref().map(|c| (r, c)))
                .collect(),
        ));
    }
    for band in SNR_BANDS {
        out.push((
            format!("Rice, {}, isotropic", band_label(band)),
            rows.iter()
                .filter(|r| in_band(r, band) && !anisotropic(r))
                .map(|r| (r, &r.rice))
                .collect(),
        ));
    }
    out.push((
        "Rice, anisotropic (S1, S2) noise, any SNR_p".to_string(),
        rows.iter()
            .filter(|r| anisotropic(r))
            .map(|r| (r, &r.rice))
            .collect(),
    ));
    out
}

fn summaries(groups: Vec<Group<'_>>) -> Vec<GroupSummary> {
    groups
        .into_iter()
        .filter_map(|(label, members)| {
            let cs: Vec<&Comparison> = members.iter().map(|(_, c)| *c).collect();
            summarise(&label, &cs)
        })
        .collect()
}

/// The summary's groups of the analytic method: all points; each polarised-SNR band
/// ([`SNR_BANDS`]) split by isotropy of the `(S1, S2)` noise; the read-noise-limited points.
/// Empty groups are left out.
pub fn groups(rows: &[Row]) -> Vec<GroupSummary> {
    summaries(group_rows(rows))
}

/// The same summary for the Taylor and Rice approximations (for reference): Taylor per band,
/// Rice per band on isotropic noise and on anisotropic noise. Empty groups are left out.
pub fn approximation_groups(rows: &[Row]) -> Vec<GroupSummary> {
    summaries(approx_group_rows(rows))
}

fn pct(x: f64) -> String {
    format!("{:.2} %", 100.0 * x)
}

/// Largest `|z|` per statistic over `members`, from `f`.
fn max_abs3<'a>(members: &[(&'a Row, &'a Comparison)], f: impl Fn(&Row) -> [f64; 3]) -> [f64; 3] {
    let mut m = [0.0f64; 3];
    for (r, _) in members {
        let v = f(r);
        for k in 0..3 {
            m[k] = m[k].max(v[k].abs());
        }
    }
    m
}

fn summary_table(o: &mut String, groups: &[GroupSummary]) {
    *o += "| group | points | DoLP mean: max / median abs. rel. err. | max abs z | within 4 SE | DoLP std: max / median | max abs z | within 4 SE | AoP std: max / median | max abs z | within 4 SE |\n";
    *o += "|---|---:|---|---:|---:|---|---:|---:|---|---:|---:|\n";
    for g in groups {
        let cell = |s: &StatSummary| {
            format!(
                "{} / {} | {:.1} | {:.0} %",
                pct(s.max_rel),
                pct(s.median_rel),
                s.max_z,
                100.0 * s.within_4se
            )
        };
        let _ = writeln!(
            o,
            "| {} | {} | {} | {} | {} |",
            g.label,
            g.count,
            cell(&g.dolp_mean),
            cell(&g.dolp_std),
            cell(&g.aop_std)
        );
    }
}

/// The generated file with the accuracy grid of the DoLP/AoP statistics against a Stokes-level
/// Monte Carlo, relative to docs/ (see [`GRID_COMMAND`]).
pub const GRID_REPORT_LINK: &str = "validation/dolp-aop-grid.md";

/// The report as Markdown. `command` is the command line that generated it.
pub fn markdown(rows: &[Row], sets: usize, seed: u64, command: &str) -> String {
    let mut o = String::new();
    let _ = writeln!(
        o,
        "# Validation: analytic statistics against a whole-chain Monte Carlo\n"
    );
    let _ = writeln!(
        o,
        "Generated by\n\n    {command}\n\n(release build; {sets} frame sets per point, seed {seed}; \
         the answer does not depend on the number of threads). Do not edit by hand: rerun the \
         command.\n"
    );
    let _ = writeln!(
        o,
        "A companion report, [{GRID_REPORT_LINK}]({GRID_REPORT_LINK}), checks `dolp_aop_stats` \
         alone against a Gaussian Monte Carlo of the Stokes estimate on a finer polarised-SNR \
         grid with anisotropic and correlated noise; it is generated by\n\n    {}\n",
        GRID_COMMAND
    );
    o += METHOD;
    let _ = writeln!(o, "\n## Summary\n");
    let _ = writeln!(
        o,
        "{} grid points. Relative error = (analytic - MC) / MC; z = (analytic - MC) / (MC \
         standard error). With {sets} sets the MC standard error is about {} of the DoLP \
         standard deviation for the mean and {} relative for the standard deviations, so \
         relative errors of that size are MC noise, not model error: |z| says which. The \
         groups are polarised-SNR bands (`SNR_p = p / sigma_p`), split by whether the (S1, S2) \
         noise is isotropic; the analytic method is the same in every group.\n",
        rows.len(),
        pct(1.0 / (sets as f64).sqrt()),
        pct(1.0 / (2.0 * sets as f64).sqrt()),
    );
    summary_table(&mut o, &groups(rows));
    o += "\nWhere the differences come from: a Gaussian Monte Carlo at the Stokes level \
          (`McSource::GaussianStokes`: the analytic Stokes mean and covariance, as many draws, \
          the same statistics) sits between the two. *Analytic* = max |analytic - Gaussian MC| \
          / SE: the analytic method's own error. *Chain* = max |Gaussian MC - chain \
          MC| / sqrt(SE_gauss^2 + SE_chain^2): the chain's departure from Gaussian Stokes noise \
          (Poisson counts, rounding to whole DN). Values below about 4 are noise.\n\n";
    o += "| group | analytic: DoLP mean | DoLP std | AoP std | chain: DoLP mean | DoLP std | AoP std |\n";
    o += "|---|---:|---:|---:|---:|---:|---:|\n";
    for (label, members) in group_rows(rows).iter() {
        if members.is_empty() {
            continue;
        }
        let f = max_abs3(members, |r| r.gauss.formulas_z);
        let c = max_abs3(members, |r| r.gauss.chain_z);
        let _ = writeln!(
            o,
            "| {label} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} |",
            f[0], f[1], f[2], c[0], c[1], c[2]
        );
    }
    let _ = writeln!(
        o,
        "\n### Approximations, for reference\n\n\
         The closed-form Taylor (delta-method) and Rice approximations (`RegimeChoice::Taylor`, \
         `RegimeChoice::Rice`), evaluated at every point from the same Stokes mean and \
         covariance and compared with the same chain MC. The Taylor forms are singular at \
         `p = 0` (DoLP 0 points left out); the Rice moments assume isotropic (S1, S2) noise.\n"
    );
    summary_table(&mut o, &approximation_groups(rows));
    let cov_max = rows
        .iter()
        .map(|r| r.result.comparison.stokes_cov_error)
        .fold(0.0, f64::max);
    let sat_max = rows
        .iter()
        .map(|r| r.result.monte_carlo.saturated_fraction)
        .fold(0.0, f64::max);
    let dark: usize = rows.iter().map(|r| r.result.monte_carlo.samples_dark).sum();
    let noise = (2.0 / sets as f64).sqrt();
    let _ = writeln!(
        o,
        "\nThe linear part is exact, as it should be: over all points and all nine entries the \
         MC's Stokes covariance differs from the analytic `Sigma_S` by at most {} of the \
         diagonal scale, {:.1} times the MC noise of one entry ({}); the largest of {} roughly \
         normal deviates is expected near 3.5. Saturated frames: at most {} of a point's \
         frames. Sets with `S0_hat <= 0` (no DoLP): {dark} in the whole run.\n",
        pct(cov_max),
        cov_max / noise,
        pct(noise),
        9 * rows.len(),
        pct(sat_max),
    );
    o += &findings(rows, sets);
    let _ = writeln!(o, "\n## Per grid point\n");
    o += "Columns: camera; analyzer angles (deg); exposure time; mean photo-electrons per frame \
          (unpolarised part); scene DoLP and AoP (deg); polarised SNR `p / sigma_p` (a star \
          marks anisotropic (S1, S2) noise) and `S0 / sigma_S0`; then for the DoLP mean, the \
          DoLP standard deviation and the AoP standard deviation (deg): analytic, MC +- \
          standard error, relative error, z; the analytic method's estimated relative error; \
          the largest relative error of the Taylor and of the Rice approximation over the three \
          statistics (- where the Taylor forms are singular).\n\n";
    o += "| # | camera | angles | t_int (ms) | e-/frame | DoLP | AoP | SNR_p | S0 SNR | DoLP mean analytic | MC +- SE | rel. err. | z | DoLP std analytic | MC +- SE | rel. err. | z | AoP std analytic | MC +- SE | rel. err. | z | est. error | Taylor worst | Rice worst |\n";
    o += "|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---|---:|---:|---:|---|---:|---:|---:|---:|---:|\n";
    for (i, r) in rows.iter().enumerate() {
        let p = &r.point;
        let c = &r.result.comparison;
        let ag = |a: &Agreement, scale: f64| {
            format!(
                "{:.5} | {:.5} +- {:.5} | {:+.2} % | {:+.1}",
                a.analytic * scale,
                a.monte_carlo * scale,
                a.se * scale,
                100.0 * a.rel_error,
                a.z
            )
        };
        let _ = writeln!(
            o,
            "| {} | {} | {} | {:.4} | {:.0} | {} | {} | {:.2}{} | {:.1} | {} | {} | {} | {} | {} | {} |",
            i + 1,
            p.camera,
            p.angles_label(),
            p.exposure.t_int_s * 1e3,
            p.mean_electrons,
            p.dolp,
            if p.dolp == 0.0 {
                "-".to_string()
            } else {
                format!("{:.0}", p.aop_deg)
            },
            c.polarised_snr,
            if anisotropic(r) { "*" } else { "" },
            s0_snr(r),
            ag(&c.dolp_mean, 1.0),
            ag(&c.dolp_std, 1.0),
            ag(&c.aop_std, 180.0 / std::f64::consts::PI),
            r.result
                .analytic
                .stats
                .rel_error_estimate
                .map_or("-".to_string(), |e| format!("{e:.0e}")),
            r.taylor.as_ref().map_or("-".to_string(), |t| pct(max_rel(t))),
            pct(max_rel(&r.rice)),
        );
    }
    o
}

/// The largest of `f` over `rows` (where defined), with the row's index.
fn worst(rows: &[Row], f: impl Fn(&Row) -> Option<f64>) -> Option<(usize, f64)> {
    rows.iter()
        .enumerate()
        .filter_map(|(i, r)| f(r).map(|v| (i, v)))
        .max_by(|a, b| a.1.total_cmp(&b.1))
}

fn max_rel(c: &Comparison) -> f64 {
    c.dolp_mean
        .rel_error
        .abs()
        .max(c.dolp_std.rel_error.abs())
        .max(c.aop_std.rel_error.abs())
}

fn max3(v: [f64; 3]) -> f64 {
    v.iter().fold(0.0f64, |m, z| m.max(z.abs()))
}

fn chain_max_z(c: &Comparison) -> f64 {
    max3([c.dolp_mean.z, c.dolp_std.z, c.aop_std.z])
}

fn point_label(rows: &[Row], i: usize) -> String {
    let r = &rows[i];
    format!(
        "point #{}: {} {} at {:.0} e-/frame, DoLP {}, SNR_p {:.2}, S0 SNR {:.1}{}",
        i + 1,
        r.point.camera,
        r.point.angles_label(),
        r.point.mean_electrons,
        r.point.dolp,
        r.result.comparison.polarised_snr,
        s0_snr(r),
        if anisotropic(r) {
            ", anisotropic (S1, S2) noise"
        } else {
            ""
        }
    )
}

/// What the report says about where the model and the approximations fail, with the run's
/// numbers.
fn findings(rows: &[Row], sets: usize) -> String {
    let mut o = String::from("### Findings\n\n");
    let t = RICE_SNR_THRESHOLD;
    let n = rows.len();
    let outside = rows
        .iter()
        .filter(|r| chain_max_z(&r.result.comparison) >= 4.0)
        .count();
    let formulas_out = rows
        .iter()
        .filter(|r| max3(r.gauss.formulas_z) >= 4.0)
        .count();
    let chain_out = rows.iter().filter(|r| max3(r.gauss.chain_z) >= 4.0).count();
    let _ = writeln!(
        o,
        "- {outside} of {n} points have some statistic 4 or more standard errors from the \
         chain MC. The analytic method is 4 or more standard errors from the Gaussian Stokes MC \
         (its own model) on {formulas_out} of them; the chain differs from Gaussian Stokes \
         noise by that much on {chain_out}: the items below say where and why.",
    );
    if let Some((i, z)) = worst(rows, |r| Some(max3(r.gauss.formulas_z))) {
        let est = rows
            .iter()
            .filter_map(|r| r.result.analytic.stats.rel_error_estimate)
            .fold(0.0, f64::max);
        let exact = rows
            .iter()
            .filter(|r| r.result.analytic.stats.method == StatsMethod::Integration)
            .count();
        let resolution = 1.0 / (2.0 * sets as f64).sqrt();
        let verdict = if z < 4.0 && est < 0.1 * resolution {
            "no difference is resolved, so what the analytic values leave out against the \
             chain MC is the chain's departure from Gaussian Stokes noise"
                .to_string()
        } else {
            format!(
                "{formulas_out} points are 4 or more standard errors off: the method's own \
                 error is resolved there (MC resolution about {})",
                pct(resolution)
            )
        };
        let _ = writeln!(
            o,
            "- **The analytic method against its own model (Gaussian Stokes noise): largest \
             difference {z:.1} standard errors** ({}), over all {n} points and three \
             statistics, every polarised-SNR band and both noise shapes. The integration is \
             used at {exact} of {n} points, with a largest estimated relative error of \
             {est:.0e}; {verdict}.",
            point_label(rows, i)
        );
    }
    for band in SNR_BANDS {
        if let Some((i, v)) = worst(rows, |r| {
            (in_band(r, band) && s0_snr(r) >= S0_SNR_LOW).then(|| max_rel(&r.result.comparison))
        }) {
            let z = rows
                .iter()
                .filter(|r| in_band(r, band) && s0_snr(r) >= S0_SNR_LOW)
                .map(|r| chain_max_z(&r.result.comparison))
                .fold(0.0, f64::max);
            let _ = writeln!(
                o,
                "- **{}, S0 SNR >= {S0_SNR_LOW}: within {} of the chain MC on every statistic, \
                 at most {z:.1} standard errors** ({}).",
                band_label(band),
                pct(v),
                point_label(rows, i)
            );
        }
    }
    let low_s0: Vec<f64> = rows
        .iter()
        .filter(|r| s0_snr(r) < S0_SNR_LOW)
        .map(s0_snr)
        .collect();
    if let Some((i, _)) = worst(rows, |r| {
        (s0_snr(r) < S0_SNR_LOW).then(|| r.result.comparison.dolp_std.rel_error.abs())
    }) {
        let g = &rows[i].gauss;
        let (lo, hi) = low_s0
            .iter()
            .fold((f64::MAX, 0.0f64), |(a, b), &x| (a.min(x), b.max(x)));
        let c = &rows[i].result.comparison.dolp_std;
        let gv = g.values[1];
        let _ = writeln!(
            o,
            "- **Read-noise-limited frames: the DoLP's denominator is noisy** (`S0 / sigma_S0` \
             from {lo:.1} to {hi:.1} on the {} points below {S0_SNR_LOW}). The integration \
             carries the `S0` noise and its correlation with `(S1, S2)` to convergence: at the \
             worst point ({}) the analytic DoLP standard deviation is {:.1} standard errors from \
             a Gaussian Stokes MC{}. The chain's is {} below that Gaussian MC ({:.1} \
             standard errors): with photon counts the polarised noise of a set grows with its \
             own total, the frames' counts being multinomial given the total, so `p_hat` rises \
             with `S0_hat` and their ratio spreads less than with the Gaussian Stokes noise of \
             the model; net {} against the chain.",
            low_s0.len(),
            point_label(rows, i),
            g.formulas_z[1].abs(),
            if g.formulas_z[1].abs() < 4.0 {
                " (not resolved)"
            } else {
                ""
            },
            pct(((c.monte_carlo - gv) / gv).abs()),
            g.chain_z[1].abs(),
            pct(c.rel_error.abs()),
        );
    }
    if let Some((i, v)) = worst(rows, |r| Some(max3(r.gauss.chain_z))) {
        let r = &rows[i];
        let sigma_dn = r.result.analytic.signal.cov_dn[(0, 0)].max(0.0).sqrt();
        let _ = writeln!(
            o,
            "- **The chain against Gaussian Stokes noise.** On {chain_out} of {n} points the \
             whole-chain MC differs from a Gaussian MC of the same Stokes mean and covariance by \
             4 or more standard errors on some statistic; the largest difference is {v:.1} ({}; \
             one DN is {:.0} e-, the frame noise {:.2} DN). Poisson counts are skewed \
             (`1/sqrt(mu)`), make `p_hat` depend on `S0_hat` (above) and rounding puts the \
             Stokes estimates on a lattice: the model keeps their variance (shot noise and \
             1/12 DN^2) but not their shape.",
            point_label(rows, i),
            1.0 / r.point.model.camera().gain_dn_per_e,
            sigma_dn
        );
    }
    let near = (t, 5.0);
    let in_near = |r: &Row| in_band(r, near) && r.taylor.is_some();
    if let Some((i, v)) = worst(rows, |r| {
        in_near(r)
            .then(|| r.taylor.as_ref().map(|c| c.dolp_std.rel_error.abs()))
            .flatten()
    }) {
        let aop = worst(rows, |r| {
            in_near(r)
                .then(|| r.taylor.as_ref().map(|c| c.aop_std.rel_error.abs()))
                .flatten()
        })
        .map_or(0.0, |(_, v)| v);
        let own = worst(rows, |r| in_near(r).then(|| max_rel(&r.result.comparison)))
            .map_or(0.0, |(_, v)| v);
        let _ = writeln!(
            o,
            "- **Taylor approximation just above the threshold ({}): the first-order DoLP \
             standard deviation is off by up to {}** ({}) **and the AoP standard deviation by up \
             to {}**; the analytic method by at most {} on any statistic of the same points. \
             The delta method's variances leave out terms of relative order `1/SNR_p^2`, and \
             anisotropic noise adds to them.",
            band_label(near),
            pct(v),
            point_label(rows, i),
            pct(aop),
            pct(own)
        );
    }
    if let Some((i, v)) = worst(rows, |r| {
        (r.result.comparison.polarised_snr < t)
            .then(|| r.taylor.as_ref().map(|c| c.dolp_mean.rel_error.abs()))
            .flatten()
    }) {
        let _ = writeln!(
            o,
            "- **The Taylor approximation fails below a polarised SNR of {t}**, as MODEL.md \
             section 7 says: the second-order DoLP mean is off by up to {} there ({}; the \
             `sigma^2 / (2 p)` term diverges as `p -> 0`).",
            pct(v),
            point_label(rows, i)
        );
    }
    if let Some((i, v)) = worst(rows, |r| anisotropic(r).then(|| max_rel(&r.rice))) {
        let own = worst(rows, |r| {
            (anisotropic(r) && s0_snr(r) >= S0_SNR_LOW).then(|| max_rel(&r.result.comparison))
        })
        .map_or(0.0, |(_, v)| v);
        let _ = writeln!(
            o,
            "- **The Rice approximation assumes isotropic (S1, S2) noise.** 0/45/90 (Pickering) \
             has `var S2 = 3 var S1` for ideal analyzers; the Rice moments then use the \
             isotropic equivalent `(var S1 + var S2)/2` (and warn), and are off by up to {} on \
             some statistic ({}); the analytic method, which integrates over the anisotropic \
             covariance, by at most {} on the anisotropic points with S0 SNR >= {S0_SNR_LOW}. \
             The symmetric sets (0/60/120, 0/45/90/135, six angles) are isotropic up to the \
             shot-noise differences between the frames of a strongly polarised scene.",
            pct(v),
            point_label(rows, i),
            pct(own)
        );
    }
    if let Some((i, v)) = worst(rows, |r| {
        (!anisotropic(r) && s0_snr(r) < S0_SNR_LOW).then(|| r.rice.dolp_std.rel_error.abs())
    }) {
        let s = s0_snr(&rows[i]);
        let _ = writeln!(
            o,
            "- **The Rice approximation on a noisy denominator:** it treats `p_hat / S0_hat` to \
             first order in the `S0` noise and leaves out terms of relative size up to \
             `3 (sigma_S0/S0)^2` in the DoLP variance ({} at S0 SNR {s:.1}); on the isotropic \
             read-noise-limited points its DoLP standard deviation is off by up to {} ({}).",
            pct(3.0 / (s * s)),
            pct(v),
            point_label(rows, i)
        );
    }
    let _ = writeln!(
        o,
        "- At {sets} sets a relative error below about {} on the standard deviations, or a \
         |z| below about 3, is not resolved: the MC cannot tell the model from the truth there.",
        pct(3.0 / (2.0 * sets as f64).sqrt())
    );
    o
}

const METHOD: &str = "## Method\n\n\
For each grid point (camera, analyzer angles, exposure time, scene Stokes radiance):\n\n\
- **Analytic** (`polar_model::validation::analytic_products`): `SensorModel::signal` gives the \
frames' mean and covariance in DN (EMVA 1288 linear model: shot, dark, read and quantisation \
noise, MODEL.md section 6); dark subtraction and scaling by `1/(K G)` give the intensities' \
covariance; the Stokes estimator (OLS for isotropic intensity noise, GLS otherwise; here GLS, \
since shot noise differs between frames) gives `Sigma_S`; `dolp_aop_stats` \
(`RegimeChoice::Auto`, MODEL.md section 7) gives the DoLP mean and standard deviation and the \
AoP standard deviation of the Gaussian Stokes estimate `N(mu_S, Sigma_S)`. It uses one method \
at every polarised SNR `p / sigma_p` and for any covariance: polar integration over (S1, S2) \
with the radial moments in closed form, Gauss-Hermite quadrature in S0 and a series in `1/S0`, \
with an estimate of its own relative error.\n\
- **Monte Carlo** (`polar_model::validation::simulate_products`): frame sets drawn through the \
sensor chain of `polar_model::montecarlo` (Poisson photo-electrons and dark electrons, full well, \
Gaussian read noise, gain and offset, rounding to whole DN, the ADC's range), each set \
dark-subtracted, scaled and turned into a Stokes estimate by the same estimator, then into a \
DoLP and an AoP. DoLP: sample mean and standard deviation with their standard errors \
(`s/sqrt(n)`; `sqrt((m4 - m2^2)/n)/(2s)` by the delta method). AoP: root-mean-square of the \
deviations from the AoP of the mean Stokes vector, wrapped into (-90, 90] deg, which is how the \
analytic AoP standard deviation is defined (it includes the AoP bias). Seeded and parallel: \
chunks of 1024 sets, each with its own SplitMix64 stream from (seed, chunk), combined in chunk \
order.\n\
- **Grid**: the two example cameras (examples/cameras/ccd_seed.toml: 10 e- read noise, 40 000 e- \
full well, K = 0.1 DN/e-; cmos_modern.toml: 2.5 e-, 10 000 e-, K = 0.35 DN/e-) through a flat \
500-600 nm band, a scene of S0 = 0.1 W m^-2 sr^-1 at exposure times giving three noise levels \
(mean photo-electrons per frame: read-noise limited `max(sigma_d^2, 20)`, 5 % and 45 % of the \
full well; the brightest frame of a DoLP 0.9 scene is then at 85 % of the full well, below \
saturation); angle sets 0/60/120, 0/45/90, 0/45/90/135 and six equally spaced (0/30/.../150); \
DoLP 0, 0.02, 0.1, 0.3, 0.9 at AoP 15 and 60 deg (DoLP 0 once).\n\
- A third estimate, a Gaussian MC at the Stokes level (`McSource::GaussianStokes`: `N(mean, \
Sigma_S)` of the analytic path, as many draws, the same statistics), separates the analytic \
method's own error from the chain's departure from Gaussian Stokes noise.\n\
- The closed-form Taylor (delta-method) and Rice approximations are evaluated at every point \
from the same Stokes mean and covariance and compared with the same MC, for reference.\n";

/// Runs the report's grid and writes the Markdown to `out`. Returns the rows.
pub fn write_report(
    out: &Path,
    sets: usize,
    seed: u64,
    command: &str,
) -> Result<Vec<Row>, ValidationError> {
    let points = GridSpec::report()?.points()?;
    let rows = run(&points, sets, seed)?;
    let text = markdown(&rows, sets, seed, command);
    std::fs::write(out, text).map_err(|source| ValidationError::Io {
        path: out.to_path_buf(),
        source,
    })?;
    Ok(rows)
}
