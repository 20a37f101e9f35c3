//! `polarimeter report study`: Meng (2012)'s Chapter 4 trade studies (Sec. 4.2), each a sweep of
//! one parameter of the scene or the sensor through the whole analytical chain of MODEL.md:
//!
//! scene (Eqs. 3.21-3.31) -> sensor frames (Sec. 3.2, MODEL.md section 6) -> Stokes estimate and
//! DoLP moments (Sec. 3.3, MODEL.md section 7) -> metrics (Sec. 4.1, MODEL.md section 8).
//!
//! Two targets, black paint and glass, are each compared with an asphalt background; the three
//! are materials of the scene file (`--paint`, `--glass`, `--background` name them). For every
//! swept value and every class the study computes:
//!
//! * the class's mean Stokes radiance and its covariance `Sigma_LS = Sigma_g + Sigma_v` at the
//!   aperture ([`polar_model::scene::Prepared::evaluate`]);
//! * the N analyzer frames' mean and covariance in DN ([`SensorModel::signal`]):
//!   `Sigma_y = K^2 G^2 W Sigma_LS W^T + F_n Sigma_n`;
//! * the Stokes estimate's covariance from the dark-subtracted, scaled frames
//!   `I_hat = (y - K mu_I t - b) / (K G)`, `Sigma_I = Sigma_y / (K G)^2`, by least squares
//!   ([`stokes_cov_from_intensity_cov`]: GLS, since shot noise and clutter make `Sigma_I`
//!   non-isotropic);
//! * the DoLP mean and standard deviation of that estimate ([`dolp_aop_stats`], Taylor or Rice
//!   regime, reported).
//!
//! **DoLP SNR** (Meng (2012) Sec. 4.1.1, "strength of polarimetric signature"; MODEL.md section 8):
//! `E[DoLP_hat] / sqrt(Var[DoLP_hat])` of one class, scene clutter (`Sigma_g + Sigma_v`) and
//! sensor noise included. It is bounded by the clutter limit (the same with `F_n = 0`), which
//! it approaches as the integration time grows. Beside it the study reports the **DoLP contrast
//! SNR** `|E[DoLP_t] - E[DoLP_b]| / sqrt(Var[DoLP_t] + Var[DoLP_b])`, the separation of a target
//! from the background in DoLP alone.
//!
//! **Detection** (Meng (2012) Sec. 4.1.2; MODEL.md sections 8-9), each target against the background,
//! at the false-alarm rate `pfa` (default 1e-3):
//! * SCR `d^T Sigma_b^-1 d` in the N frames (`d` the difference of the class means in DN,
//!   `Sigma_b` the background's full frame covariance);
//! * the linear matched filter and the RX detector on the N frames ([`metrics::matched_filter`],
//!   [`metrics::rx`]); RX only where the model's own error bound `pd_error` is below
//!   [`RX_MAX_PD_ERROR`] (far in the tail a Chernoff bound answers for Ruben's series);
//!   elsewhere the CSV leaves it empty;
//! * the DoLP threshold detector on the two classes' DoLP moments ([`metrics::dolp_threshold`]),
//!   where both S0 estimates are good to [`DOLP_MAX_S0_REL_STD`] (the moments expand
//!   `1 / S0_hat`); elsewhere the CSV leaves it empty and gives `s0_rel_std` per class.
//!
//! The ROC families in the figures are the DoLP threshold detector's. The targets also differ
//! from asphalt in brightness (in examples/study.toml's glint, glass has 14 times and paint 1.7
//! times asphalt's S0), so the matched filter and RX, which work on the frames' intensities,
//! detect them by brightness wherever the intensities differ (Pd near 1 in most rows of the CSV);
//! the DoLP detector measures the polarimetric signature alone, which is what Meng (2012)'s Ch. 4
//! studies.
//!
//! The six studies (Meng (2012) Sec. 4.2):
//! * `sources` (4.2.1): direct sun only, skylight only, sun + sky, sun + sky + path radiance
//!   (Eq. 3.24 term by term, from [`polar_model::scene::Prepared::boresight_terms`] at the
//!   boresight ray; the clutter of these rows is the texture `Sigma_v` rebuilt from the included
//!   reflected terms by the scene model's own rule, since the geometry variation `Sigma_g` cannot
//!   be split by source), and the full scene model (field mean, `Sigma_g + Sigma_v`) as a
//!   reference row;
//! * `altitude` (4.2.2): sensor height above the ground, m;
//! * `geometry` (4.2.5): the specular plane: sun zenith = view angle off nadir = theta, the sensor
//!   looking towards the sun's azimuth (relative azimuth 180 deg), through the glass's Brewster
//!   angle 56.66 deg;
//! * `roughness` (4.2.4): the facet-slope roughness sigma (Eq. 3.13) of both targets (the
//!   background keeps its own);
//! * `noise-factor` (4.2.6): the sensor noise factor `F_n` (scales the sensor-noise variance by
//!   default, or its standard deviation; MODEL.md section 6);
//! * `integration-time` (4.2.7): ms.
//!
//! Each writes `<kind>.csv` (one row per swept value and target), `<kind>_roc.csv` (the ROC
//! curves) and `<kind>.png` (DoLP SNR, Pd at `pfa` of the three detectors, and the DoLP
//! detector's ROC family for each target), drawn by [`crate::study_files`].

use crate::commands::{load_scene, CommandError};
use crate::figures::FigureError;
use clap::Args;
use nalgebra::{DMatrix, Matrix3, Vector3};
use polar_model::metrics::{self, ClassStats};
use polar_model::pbrdf::{Microfacet, Surface};
use polar_model::polarization::Stokes;
use polar_model::scene::{Prepared, SceneMaterial, SceneSpec, Texture};
use polar_model::scene_file::Scene;
use polar_model::sensor::{Camera, Exposure, NoiseFactor, SensorModel};
use polar_model::stats::{dolp_aop_stats, stokes_cov_from_intensity_cov, Regime, RegimeChoice};
use polar_model::ModelError;
use std::path::PathBuf;

/// The false-alarm rate at which Pd is reported by default.
pub const DEFAULT_PFA: f64 = 1e-3;

/// Largest relative noise of the S0 estimate, `sqrt(Var[S0_hat]) / S0`, at which the DoLP
/// detector is reported: the DoLP moments expand `1 / S0_hat` about its mean (MODEL.md
/// section 7), which needs S0 well above its noise; 1/3 is an S0 SNR of 3, the threshold the
/// model uses for the polarised SNR ([`polar_model::stats::RICE_SNR_THRESHOLD`]).
pub const DOLP_MAX_S0_REL_STD: f64 = 1.0 / 3.0;

/// Largest `pd_error` of an RX ROC that the study reports.
pub const RX_MAX_PD_ERROR: f64 = 1e-3;

/// The roughness study's second view: the look azimuth turned this far from the specular plane,
/// where a smooth surface's lobe does not reach and a rough one's does (Meng (2012)'s Fig. 3.6
/// "spreading"), degrees.
pub const OFF_SPECULAR_AZIMUTH_DEG: f64 = 30.0;

/// Brewster angle of glass, n = 1.52 (`atan(1.52)`, MODEL.md section 2), degrees.
pub const GLASS_BREWSTER_DEG: f64 = 56.659_893_078_524_83;

/// Errors of a study: every message names the field or file at fault.
#[derive(Debug, thiserror::Error)]
pub enum StudyError {
    /// The scene or camera file could not be read or parsed (the message names the file).
    #[error("{0}")]
    Input(String),
    /// A material the study needs is not in the scene.
    #[error(
        "{field} = {name:?}: the scene {scene} has no material of that name (it has: {available})"
    )]
    MissingMaterial {
        /// The flag naming the material (`paint`, `glass`, `background`).
        field: &'static str,
        /// The name looked for.
        name: String,
        /// The scene file.
        scene: String,
        /// The scene's material names.
        available: String,
    },
    /// A setting or swept value outside its domain, or a model evaluation that failed at one
    /// point of a sweep (the message names the study, the value and the model's field).
    #[error("{context}: {source}")]
    Model {
        /// Where: the study and the swept value.
        context: String,
        /// The model's error, naming its field.
        #[source]
        source: ModelError,
    },
    /// A flag's value is invalid.
    #[error("{field} is invalid: {reason}")]
    Invalid {
        /// The flag, with underscores.
        field: &'static str,
        /// What is wrong and what is allowed.
        reason: String,
    },
    /// Writing a CSV or drawing a PNG failed.
    #[error(transparent)]
    Figure(#[from] FigureError),
}

impl From<CommandError> for StudyError {
    fn from(e: CommandError) -> Self {
        StudyError::Input(e.to_string())
    }
}

fn at(context: impl Into<String>) -> impl FnOnce(ModelError) -> StudyError {
    let context = context.into();
    move |source| StudyError::Model { context, source }
}

/// One of the six trade studies.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StudyKind {
    /// Meng (2012) Sec. 4.2.1: which radiometric sources light the scene.
    Sources,
    /// Meng (2012) Sec. 4.2.2: sensor platform altitude.
    Altitude,
    /// Meng (2012) Sec. 4.2.5: sun and view geometry in the specular plane.
    Geometry,
    /// Meng (2012) Sec. 4.2.4: surface roughness of the targets.
    Roughness,
    /// Meng (2012) Sec. 4.2.6: sensor noise factor.
    NoiseFactor,
    /// Meng (2012) Sec. 4.2.7: integration time.
    IntegrationTime,
}

/// The command line's choice: one study or all.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum StudySelection {
    /// Direct sun, skylight and path radiance, alone and together (Meng (2012) Sec. 4.2.1).
    Sources,
    /// Sensor altitude, 10 m to 10 km (Sec. 4.2.2).
    Altitude,
    /// Specular sun/view angle through Brewster (Sec. 4.2.5).
    Geometry,
    /// Target roughness sigma 0.05 to 0.7 (Sec. 4.2.4).
    Roughness,
    /// Sensor noise factor 1 to 10 (Sec. 4.2.6).
    NoiseFactor,
    /// Integration time 0.002 to 2 ms (Sec. 4.2.7).
    IntegrationTime,
    /// All six.
    All,
    /// Adaptive polarimetric target detection against conventional sets (Meng (2012)'s Table 5.2;
    /// `study_aptd`).
    Aptd,
    /// SCR of conventional and optimal sets against integration time (Meng (2012) Fig. 5.1;
    /// `study_scr`).
    ScrTime,
    /// The distribution of SCR over all 3-angle sets (Meng (2012) Fig. 5.2; `study_scr`).
    ScrSets,
    /// DoLP variation over the field of view against roughness, and its ROC (Meng (2012)
    /// Sec. 4.2.3; `study_fov`).
    Fov,
}

impl StudySelection {
    /// The studies selected.
    pub fn kinds(self) -> Vec<StudyKind> {
        match self {
            StudySelection::Sources => vec![StudyKind::Sources],
            StudySelection::Altitude => vec![StudyKind::Altitude],
            StudySelection::Geometry => vec![StudyKind::Geometry],
            StudySelection::Roughness => vec![StudyKind::Roughness],
            StudySelection::NoiseFactor => vec![StudyKind::NoiseFactor],
            StudySelection::IntegrationTime => vec![StudyKind::IntegrationTime],
            StudySelection::All => StudyKind::ALL.to_vec(),
            StudySelection::Aptd
            | StudySelection::ScrTime
            | StudySelection::ScrSets
            | StudySelection::Fov => Vec::new(),
        }
    }
}

/// The labels of the `sources` study's rows, in order.
pub const SOURCE_LABELS: [&str; 5] = [
    "sun only",
    "sky only",
    "sun + sky",
    "sun + sky + path",
    "scene model (field)",
];

impl StudyKind {
    /// All six, in the order `all` runs them.
    pub const ALL: [StudyKind; 6] = [
        StudyKind::Sources,
        StudyKind::Altitude,
        StudyKind::Geometry,
        StudyKind::Roughness,
        StudyKind::NoiseFactor,
        StudyKind::IntegrationTime,
    ];

    /// The file stem and command-line name.
    pub fn name(self) -> &'static str {
        match self {
            StudyKind::Sources => "sources",
            StudyKind::Altitude => "altitude",
            StudyKind::Geometry => "geometry",
            StudyKind::Roughness => "roughness",
            StudyKind::NoiseFactor => "noise-factor",
            StudyKind::IntegrationTime => "integration-time",
        }
    }

    /// The swept parameter, with its unit (CSV column and axis title).
    pub fn parameter(self) -> &'static str {
        match self {
            StudyKind::Sources => "sources",
            StudyKind::Altitude => "altitude_m",
            StudyKind::Geometry => "specular_angle_deg",
            StudyKind::Roughness => "target_sigma",
            StudyKind::NoiseFactor => "noise_factor",
            StudyKind::IntegrationTime => "t_int_ms",
        }
    }

    pub(crate) fn axis_title(self) -> &'static str {
        match self {
            StudyKind::Sources => "radiometric sources (Eq. 3.24 terms)",
            StudyKind::Altitude => "sensor altitude (m, log)",
            StudyKind::Geometry => "sun zenith = view angle off nadir, specular plane (deg)",
            StudyKind::Roughness => "target roughness sigma (facet slope, Eq. 3.13)",
            StudyKind::NoiseFactor => "sensor noise factor F_n",
            StudyKind::IntegrationTime => "integration time (ms, log)",
        }
    }

    pub(crate) fn log_axis(self) -> bool {
        matches!(self, StudyKind::Altitude | StudyKind::IntegrationTime)
    }

    /// The default sweep (for `sources`, the row indices of [`SOURCE_LABELS`]).
    pub fn default_values(self) -> Vec<f64> {
        match self {
            StudyKind::Sources => (0..SOURCE_LABELS.len()).map(|i| i as f64).collect(),
            StudyKind::Altitude => vec![
                10.0, 30.0, 100.0, 300.0, 1000.0, 2000.0, 3000.0, 5000.0, 10000.0,
            ],
            StudyKind::Geometry => vec![
                20.0, 30.0, 40.0, 45.0, 50.0, 52.5, 55.0, 56.66, 58.0, 60.0, 62.5, 65.0, 70.0,
                75.0, 80.0,
            ],
            StudyKind::Roughness => vec![0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7],
            StudyKind::NoiseFactor => vec![1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 7.0, 10.0],
            StudyKind::IntegrationTime => {
                vec![0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0]
            }
        }
    }

    /// Checks one swept value; errors name the parameter.
    fn check(self, v: f64) -> Result<(), StudyError> {
        let (lo, hi, allowed) = match self {
            StudyKind::Sources => (0.0, 4.0, "a row index 0..=4"),
            StudyKind::Altitude => (0.1, 1e5, "[0.1, 1e5] m"),
            StudyKind::Geometry => (0.0, 85.0, "[0, 85] deg"),
            StudyKind::Roughness => (1e-3, 10.0, "[1e-3, 10]"),
            StudyKind::NoiseFactor => (0.0, 1e6, "[0, 1e6]"),
            StudyKind::IntegrationTime => (1e-6, 1e8, "(0, 1e8] ms"),
        };
        ModelError::check_range(self.parameter(), v, lo, hi, allowed)
            .map(|_| ())
            .map_err(at(format!("study {}", self.name())))
    }
}

/// What the noise factor scales.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Default)]
pub enum NoiseScaling {
    /// `F_n` multiplies the sensor-noise variance (the default; MODEL.md section 6).
    #[default]
    Variance,
    /// `F_n` multiplies the sensor-noise standard deviation.
    Std,
}

impl NoiseScaling {
    fn factor(self, f: f64) -> NoiseFactor {
        match self {
            NoiseScaling::Variance => NoiseFactor::Variance(f),
            NoiseScaling::Std => NoiseFactor::StdDev(f),
        }
    }
}

/// `polarimeter report study KIND`: Meng (2012)'s Ch. 4 trade studies (see the module docs).
#[derive(Debug, Clone, Args)]
pub struct StudyArgs {
    /// Which study (or all).
    #[arg(value_enum)]
    pub kind: StudySelection,
    /// The scene (TOML; examples/study.toml is made for these studies).
    #[arg(long)]
    pub scene: PathBuf,
    /// The camera (TOML).
    #[arg(long, default_value = "examples/cameras/ccd_seed.toml")]
    pub camera: PathBuf,
    /// Output directory for `<kind>.csv`, `<kind>_roc.csv` and `<kind>.png`.
    #[arg(long, default_value = "docs/studies")]
    pub out: PathBuf,
    /// Analyzer angles, degrees, comma-separated (at least 3 distinct modulo 180).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, default_values_t = [0.0, 45.0, 90.0, 135.0])]
    pub angles_deg: Vec<f64>,
    /// Integration time of every study but `integration-time`, ms (the default keeps the
    /// glass glint of examples/study.toml below the ccd_seed camera's full well).
    #[arg(long, default_value_t = 0.05)]
    pub t_int_ms: f64,
    /// Sensor noise factor of every study but `noise-factor`.
    #[arg(long, default_value_t = 1.0)]
    pub noise_factor: f64,
    /// What the noise factor scales: variance (default) or std.
    #[arg(long, value_enum, default_value_t = NoiseScaling::Variance)]
    pub noise_factor_scales: NoiseScaling,
    /// Relative tolerance of the scene model's mean S0, [1e-10, 0.1].
    #[arg(long, default_value_t = 1e-3)]
    pub tolerance: f64,
    /// False-alarm rate at which Pd is reported, (0, 1).
    #[arg(long, default_value_t = DEFAULT_PFA)]
    pub pfa: f64,
    /// The scene's black-paint target material.
    #[arg(long, default_value = "black_paint")]
    pub paint: String,
    /// The scene's glass target material.
    #[arg(long, default_value = "glass")]
    pub glass: String,
    /// The scene's asphalt background material.
    #[arg(long, default_value = "asphalt")]
    pub background: String,
    /// Swept values replacing the study's default sweep (one study only, not `sources`).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub values: Vec<f64>,
}

/// The settings of a study besides the scene and camera.
#[derive(Debug, Clone, PartialEq)]
pub struct StudySettings {
    /// Analyzer angles, degrees.
    pub angles_deg: Vec<f64>,
    /// Integration time, ms (all studies but `integration-time`).
    pub t_int_ms: f64,
    /// Noise factor (all studies but `noise-factor`).
    pub noise_factor: f64,
    /// What the noise factor scales.
    pub noise_scaling: NoiseScaling,
    /// Scene tolerance.
    pub tolerance: f64,
    /// False-alarm rate for Pd.
    pub pfa: f64,
    /// Material names: black paint, glass, background.
    pub materials: [String; 3],
}

impl Default for StudySettings {
    fn default() -> Self {
        StudySettings {
            angles_deg: vec![0.0, 45.0, 90.0, 135.0],
            t_int_ms: 0.05,
            noise_factor: 1.0,
            noise_scaling: NoiseScaling::Variance,
            tolerance: 1e-3,
            pfa: DEFAULT_PFA,
            materials: ["black_paint".into(), "glass".into(), "asphalt".into()],
        }
    }
}

/// A loaded study: scene, camera through the scene's band, the three materials.
#[derive(Debug, Clone)]
pub struct Study {
    scene_label: String,
    spec: SceneSpec,
    /// Black paint, glass, background.
    materials: [SceneMaterial; 3],
    sensor: SensorModel,
    angles_rad: Vec<f64>,
    settings: StudySettings,
}

/// Statistics of one class at one swept value.
#[derive(Debug, Clone, PartialEq)]
pub struct ClassResult {
    /// Material name in the scene.
    pub name: String,
    /// Mean Stokes radiance at the aperture, camera frame, W m^-2 sr^-1 (band).
    pub radiance_mean: [f64; 3],
    /// DoLP of the mean radiance, `sqrt(S1^2 + S2^2) / S0`.
    pub dolp_true: f64,
    /// Mean of the DoLP estimate.
    pub dolp_mean: f64,
    /// Standard deviation of the DoLP estimate (clutter and sensor noise).
    pub dolp_std: f64,
    /// `dolp_mean / dolp_std` (module docs).
    pub dolp_snr: f64,
    /// The DoLP clutter limit: the DoLP SNR with the sensor noise removed (`F_n = 0`).
    pub dolp_snr_clutter_limit: f64,
    /// Regime of the DoLP moments.
    pub regime: Regime,
    /// `sqrt(Var[S0_hat]) / S0`: the DoLP moments assume it small (MODEL.md section 7); above
    /// [`DOLP_MAX_S0_REL_STD`] the DoLP detector is not reported.
    pub s0_rel_std: f64,
    /// Some frame is within 3 sigma of saturation (the linear model overstates it there).
    pub saturated: bool,
    /// The largest frame's photo-electrons.
    pub max_electrons: f64,
    /// Path radiance relative to S0, as the scene model reports it (0 when skipped).
    pub path_relative: f64,
    /// The scene model's error estimate of the mean, relative to S0.
    pub scene_error: f64,
}

/// One target against the background at one swept value.
#[derive(Debug, Clone, PartialEq)]
pub struct TargetResult {
    /// The target's statistics.
    pub class: ClassResult,
    /// `E[DoLP_t] - E[DoLP_b]`.
    pub dolp_contrast: f64,
    /// `|E[DoLP_t] - E[DoLP_b]| / sqrt(Var_t + Var_b)`.
    pub dolp_contrast_snr: f64,
    /// Signal-to-clutter ratio in the N frames.
    pub scr: f64,
    /// Matched filter on the frames.
    pub matched_filter: metrics::Roc,
    /// RX on the frames (`None` where not computed or not reliable: module docs).
    pub rx: Option<metrics::Roc>,
    /// Roughness study only: the DoLP of the target's mean radiance seen
    /// [`OFF_SPECULAR_AZIMUTH_DEG`] out of the specular plane.
    pub dolp_off_specular: Option<f64>,
    /// DoLP threshold (`None` where a class's S0 estimate is too noisy for its DoLP moments,
    /// [`ClassResult::s0_rel_std`] above [`DOLP_MAX_S0_REL_STD`], or they fall outside the
    /// Gaussian detector's domain `[0, 1.5]`).
    pub dolp: Option<metrics::Roc>,
}

/// One swept value.
#[derive(Debug, Clone, PartialEq)]
pub struct StudyPoint {
    /// The swept value (a row index for `sources`).
    pub value: f64,
    /// How it is labelled in the figure.
    pub label: String,
    /// Black paint, then glass.
    pub targets: [TargetResult; 2],
    /// The background.
    pub background: ClassResult,
}

/// A study's results.
#[derive(Debug, Clone, PartialEq)]
pub struct StudyResult {
    /// Which study.
    pub kind: StudyKind,
    /// The scene file (for captions).
    pub scene: String,
    /// Integration time used where it is not swept, ms.
    pub t_int_ms: f64,
    /// Noise factor used where it is not swept.
    pub noise_factor: f64,
    /// The false-alarm rate of the Pd columns.
    pub pfa: f64,
    /// The points, in sweep order.
    pub points: Vec<StudyPoint>,
}

/// A class's radiance statistics at the aperture.
#[derive(Debug, Clone)]
pub(crate) struct Radiance {
    mean: Vector3<f64>,
    cov: Matrix3<f64>,
    path_relative: f64,
    error: f64,
}

impl Radiance {
    pub(crate) fn from_result(r: &polar_model::scene::MaterialResult) -> Radiance {
        Radiance {
            mean: r.mean.0,
            cov: r.cov,
            path_relative: if r.terms.path.evaluated {
                r.terms.path.relative_size
            } else {
                0.0
            },
            error: r.error_estimate,
        }
    }
}

/// A class after the sensor and the processing.
struct Chain {
    frames: ClassStats,
    dolp_mean: f64,
    dolp_std: f64,
    dolp_snr_clutter_limit: f64,
    regime: Regime,
    s0_rel_std: f64,
    saturated: bool,
    max_electrons: f64,
}

/// The sensor settings of one point.
#[derive(Debug, Clone, Copy)]
pub(crate) struct SensorPoint {
    t_int_s: f64,
    noise: NoiseFactor,
}

fn snr(mean: f64, std: f64) -> f64 {
    mean / std.max(f64::MIN_POSITIVE)
}

impl Study {
    /// The scene's settings.
    pub(crate) fn spec(&self) -> &SceneSpec {
        &self.spec
    }

    /// Black paint, glass, background.
    pub(crate) fn materials(&self) -> &[SceneMaterial; 3] {
        &self.materials
    }

    /// The camera through the scene's band.
    pub(crate) fn sensor(&self) -> &SensorModel {
        &self.sensor
    }

    /// The settings.
    pub(crate) fn settings(&self) -> &StudySettings {
        &self.settings
    }

    /// The scene file, for captions.
    pub(crate) fn scene_label(&self) -> &str {
        &self.scene_label
    }

    /// Loads the scene and camera files named by `args` and checks the settings.
    pub fn load(args: &StudyArgs) -> Result<Study, StudyError> {
        let scene = load_scene(&args.scene)?;
        let text = std::fs::read_to_string(&args.camera).map_err(|e| {
            StudyError::Input(format!(
                "camera = {:?}: cannot read ({e})",
                args.camera.display().to_string()
            ))
        })?;
        let camera = Camera::from_toml_str(&text)
            .map_err(|e| StudyError::Input(format!("{}: {e}", args.camera.display())))?;
        let settings = StudySettings {
            angles_deg: args.angles_deg.clone(),
            t_int_ms: args.t_int_ms,
            noise_factor: args.noise_factor,
            noise_scaling: args.noise_factor_scales,
            tolerance: args.tolerance,
            pfa: args.pfa,
            materials: [
                args.paint.clone(),
                args.glass.clone(),
                args.background.clone(),
            ],
        };
        Study::new(&scene, &args.scene.display().to_string(), &camera, settings)
    }

    /// A study of a parsed scene and camera; `scene_label` names the scene in messages and
    /// captions. Errors name the material flag or the setting.
    pub fn new(
        scene: &Scene,
        scene_label: &str,
        camera: &Camera,
        settings: StudySettings,
    ) -> Result<Study, StudyError> {
        let fields = ["paint", "glass", "background"];
        let mut found = Vec::with_capacity(3);
        for (field, name) in fields.iter().zip(&settings.materials) {
            let m = scene
                .materials
                .iter()
                .find(|m| &m.name == name)
                .ok_or_else(|| StudyError::MissingMaterial {
                    field,
                    name: name.clone(),
                    scene: scene_label.to_string(),
                    available: scene
                        .materials
                        .iter()
                        .map(|m| m.name.as_str())
                        .collect::<Vec<_>>()
                        .join(", "),
                })?;
            found.push(m.clone());
        }
        let materials: [SceneMaterial; 3] = [found[0].clone(), found[1].clone(), found[2].clone()];
        ModelError::check_range("t_int_ms", settings.t_int_ms, 1e-6, 1e8, "(0, 1e8] ms")
            .map_err(at("study settings"))?;
        ModelError::check_range("noise_factor", settings.noise_factor, 0.0, 1e6, "[0, 1e6]")
            .map_err(at("study settings"))?;
        ModelError::check_range("tolerance", settings.tolerance, 1e-10, 0.1, "[1e-10, 0.1]")
            .map_err(at("study settings"))?;
        if !(settings.pfa.is_finite() && settings.pfa > 0.0 && settings.pfa < 1.0) {
            return Err(StudyError::Invalid {
                field: "pfa",
                reason: format!("{}: allowed (0, 1)", settings.pfa),
            });
        }
        if let Some(bad) = settings
            .angles_deg
            .iter()
            .find(|a| !a.is_finite() || a.abs() > 3600.0)
        {
            return Err(StudyError::Invalid {
                field: "angles_deg",
                reason: format!("{bad}: allowed finite values in [-3600, 3600]"),
            });
        }
        let sensor = SensorModel::new(camera, &scene.spec.band).map_err(at("camera"))?;
        let angles_rad: Vec<f64> = settings.angles_deg.iter().map(|a| a.to_radians()).collect();
        // The estimator needs W of full rank: check once, here, with the plain sensor.
        let w = sensor
            .intensities_from_stokes(&angles_rad)
            .map_err(at("angles_deg"))?;
        let n = w.nrows();
        stokes_cov_from_intensity_cov(&w, &DMatrix::identity(n, n)).map_err(at("angles_deg"))?;
        Ok(Study {
            scene_label: scene_label.to_string(),
            spec: scene.spec.clone(),
            materials,
            sensor,
            angles_rad,
            settings,
        })
    }

    pub(crate) fn base_sensor(&self) -> SensorPoint {
        SensorPoint {
            t_int_s: self.settings.t_int_ms * 1e-3,
            noise: self
                .settings
                .noise_scaling
                .factor(self.settings.noise_factor),
        }
    }

    /// The three classes' radiance statistics for `spec` and `materials`.
    pub(crate) fn scene_stats(
        &self,
        spec: &SceneSpec,
        materials: &[SceneMaterial; 3],
        context: &str,
    ) -> Result<[Radiance; 3], StudyError> {
        let p = Prepared::new(spec, self.settings.tolerance).map_err(at(context))?;
        let r = p.evaluate_all(materials).map_err(at(context))?;
        Ok([
            Radiance::from_result(&r[0]),
            Radiance::from_result(&r[1]),
            Radiance::from_result(&r[2]),
        ])
    }

    /// The sensor and processing chain of one class (module docs).
    fn chain(&self, r: &Radiance, s: SensorPoint, context: &str) -> Result<Chain, StudyError> {
        let stats = |noise: NoiseFactor| -> Result<_, StudyError> {
            let exposure = Exposure {
                t_int_s: s.t_int_s,
                radiance_mean_w_m2_sr: Stokes(r.mean),
                radiance_cov_w2_m4_sr2: r.cov,
                noise_factor: noise,
                eps_cal: 0.0,
            };
            let sig = self
                .sensor
                .signal(&self.angles_rad, &exposure)
                .map_err(at(context))?;
            let kg = self.sensor.camera().gain_dn_per_e * sig.electrons_from_radiance;
            let cov_i = &sig.cov_dn / (kg * kg);
            let est = stokes_cov_from_intensity_cov(&sig.intensities_from_stokes, &cov_i)
                .map_err(at(context))?;
            let d = dolp_aop_stats(&r.mean, &est.cov, RegimeChoice::Auto).map_err(at(context))?;
            Ok((
                sig,
                d,
                est.cov[(0, 0)].max(0.0).sqrt() / r.mean[0].abs().max(f64::MIN_POSITIVE),
            ))
        };
        let (sig, d, s0_rel_std) = stats(s.noise)?;
        let (_, limit, _) = stats(NoiseFactor::Variance(0.0))?;
        let frames = ClassStats::new("frames", sig.mean_dn.clone(), sig.cov_dn.clone())
            .map_err(at(context))?;
        Ok(Chain {
            frames,
            dolp_mean: d.dolp_mean,
            dolp_std: d.dolp_std,
            dolp_snr_clutter_limit: snr(limit.dolp_mean, limit.dolp_std),
            regime: d.regime,
            s0_rel_std,
            saturated: sig.saturated.iter().any(|&b| b),
            max_electrons: sig.electrons.max(),
        })
    }

    fn class_result(name: &str, r: &Radiance, c: &Chain) -> ClassResult {
        ClassResult {
            name: name.to_string(),
            radiance_mean: [r.mean[0], r.mean[1], r.mean[2]],
            dolp_true: Stokes(r.mean).dolp().unwrap_or(0.0),
            dolp_mean: c.dolp_mean,
            dolp_std: c.dolp_std,
            dolp_snr: snr(c.dolp_mean, c.dolp_std),
            dolp_snr_clutter_limit: c.dolp_snr_clutter_limit,
            regime: c.regime,
            s0_rel_std: c.s0_rel_std,
            saturated: c.saturated,
            max_electrons: c.max_electrons,
            path_relative: r.path_relative,
            scene_error: r.error,
        }
    }

    /// One point: the three classes through the sensor, then the two target-background pairs.
    pub(crate) fn point(
        &self,
        value: f64,
        label: String,
        radiance: &[Radiance; 3],
        s: SensorPoint,
        context: &str,
    ) -> Result<StudyPoint, StudyError> {
        let bc = self.chain(&radiance[2], s, context)?;
        let background = Study::class_result(&self.materials[2].name, &radiance[2], &bc);
        let mut targets = Vec::with_capacity(2);
        for (r, m) in radiance.iter().zip(&self.materials).take(2) {
            let tc = self.chain(r, s, context)?;
            let class = Study::class_result(&m.name, r, &tc);
            let pfa = self.settings.pfa;
            let (scr, _) = metrics::scr(&tc.frames, &bc.frames).map_err(at(context))?;
            let mf = metrics::matched_filter(&tc.frames, &bc.frames, pfa).map_err(at(context))?;
            let rx = Some(metrics::rx(&tc.frames, &bc.frames, pfa).map_err(at(context))?)
                .filter(|r| r.pd_error <= RX_MAX_PD_ERROR);
            // Out of the detector's domain only when the moments themselves are unreliable.
            let reliable = tc.s0_rel_std.max(bc.s0_rel_std) <= DOLP_MAX_S0_REL_STD;
            let dolp = if reliable {
                metrics::dolp_threshold(
                    (tc.dolp_mean, tc.dolp_std.max(f64::MIN_POSITIVE)),
                    (bc.dolp_mean, bc.dolp_std.max(f64::MIN_POSITIVE)),
                    pfa,
                )
                .ok()
            } else {
                None
            };
            let contrast = tc.dolp_mean - bc.dolp_mean;
            let spread = tc.dolp_std.hypot(bc.dolp_std);
            targets.push(TargetResult {
                class,
                dolp_contrast: contrast,
                dolp_contrast_snr: snr(contrast.abs(), spread),
                scr,
                matched_filter: mf,
                rx,
                dolp,
                dolp_off_specular: None,
            });
        }
        let glass = targets.pop();
        let paint = targets.pop();
        match (paint, glass) {
            (Some(p), Some(g)) => Ok(StudyPoint {
                value,
                label,
                targets: [p, g],
                background,
            }),
            _ => Err(StudyError::Invalid {
                field: "materials",
                reason: "internal: two targets expected".into(),
            }),
        }
    }

    /// Runs one study over `values` (its default sweep when `None`).
    pub fn run(&self, kind: StudyKind, values: Option<&[f64]>) -> Result<StudyResult, StudyError> {
        let values: Vec<f64> = match values {
            Some(v) if kind == StudyKind::Sources => {
                return Err(StudyError::Invalid {
                    field: "values",
                    reason: format!(
                        "{} values given: the sources study has fixed rows ({})",
                        v.len(),
                        SOURCE_LABELS.join(", ")
                    ),
                })
            }
            Some([]) | None => kind.default_values(),
            Some(v) => v.to_vec(),
        };
        for &v in &values {
            kind.check(v)?;
        }
        let base = self.base_sensor();
        let mut points = Vec::with_capacity(values.len());
        match kind {
            StudyKind::Sources => {
                points = self.sources()?;
            }
            StudyKind::Altitude | StudyKind::Geometry => {
                for &v in &values {
                    let context = format!("study {}, {} = {v}", kind.name(), kind.parameter());
                    let mut spec = self.spec.clone();
                    if kind == StudyKind::Altitude {
                        spec.pointing.altitude_m = v;
                    } else {
                        spec.sun_zenith_deg = v;
                        spec.pointing.off_nadir_deg = v;
                        spec.pointing.look_azimuth_deg = spec.sun_azimuth_deg;
                    }
                    let r = self.scene_stats(&spec, &self.materials, &context)?;
                    points.push(self.point(v, format_value(v), &r, base, &context)?);
                }
            }
            StudyKind::Roughness => {
                let context = format!("study {}", kind.name());
                let p = Prepared::new(&self.spec, self.settings.tolerance).map_err(at(&context))?;
                let background =
                    Radiance::from_result(&p.evaluate(&self.materials[2]).map_err(at(&context))?);
                let mut off = self.spec.clone();
                off.pointing.look_azimuth_deg =
                    (off.pointing.look_azimuth_deg + OFF_SPECULAR_AZIMUTH_DEG).rem_euclid(360.0);
                let p_off = Prepared::new(&off, self.settings.tolerance).map_err(at(&context))?;
                for &v in &values {
                    let context = format!("study {}, {} = {v}", kind.name(), kind.parameter());
                    let mut r = Vec::with_capacity(3);
                    let mut dolp_off = Vec::with_capacity(2);
                    for m in &self.materials[..2] {
                        let m = with_sigma(m, v).map_err(at(&context))?;
                        r.push(Radiance::from_result(
                            &p.evaluate(&m).map_err(at(&context))?,
                        ));
                        let o = p_off.evaluate(&m).map_err(at(&context))?;
                        dolp_off.push(o.mean.dolp().unwrap_or(0.0));
                    }
                    let r = [r[0].clone(), r[1].clone(), background.clone()];
                    let mut point = self.point(v, format_value(v), &r, base, &context)?;
                    for (t, d) in point.targets.iter_mut().zip(dolp_off) {
                        t.dolp_off_specular = Some(d);
                    }
                    points.push(point);
                }
            }
            StudyKind::NoiseFactor | StudyKind::IntegrationTime => {
                let context = format!("study {}", kind.name());
                let r = self.scene_stats(&self.spec, &self.materials, &context)?;
                for &v in &values {
                    let context = format!("study {}, {} = {v}", kind.name(), kind.parameter());
                    let s = if kind == StudyKind::NoiseFactor {
                        SensorPoint {
                            noise: self.settings.noise_scaling.factor(v),
                            ..base
                        }
                    } else {
                        SensorPoint {
                            t_int_s: v * 1e-3,
                            ..base
                        }
                    };
                    points.push(self.point(v, format_value(v), &r, s, &context)?);
                }
            }
        }
        Ok(StudyResult {
            kind,
            scene: self.scene_label.clone(),
            t_int_ms: self.settings.t_int_ms,
            noise_factor: self.settings.noise_factor,
            pfa: self.settings.pfa,
            points,
        })
    }

    /// The `sources` rows: Eq. 3.24's terms at the boresight, alone and together, then the full
    /// scene model (module docs).
    fn sources(&self) -> Result<Vec<StudyPoint>, StudyError> {
        let context = "study sources";
        let p = Prepared::new(&self.spec, self.settings.tolerance).map_err(at(context))?;
        let mut terms = Vec::with_capacity(3);
        let mut full = Vec::with_capacity(3);
        for m in &self.materials {
            terms.push(p.boresight_terms(m).map_err(at(context))?);
            full.push(Radiance::from_result(&p.evaluate(m).map_err(at(context))?));
        }
        // [direct, skylight, path] switches of each row.
        let rows: [[bool; 3]; 4] = [
            [true, false, false],
            [false, true, false],
            [true, true, false],
            [true, true, true],
        ];
        let mut points = Vec::with_capacity(SOURCE_LABELS.len());
        let base = self.base_sensor();
        for (i, on) in rows.iter().enumerate() {
            let context = format!("study sources, {}", SOURCE_LABELS[i]);
            let mut r = Vec::with_capacity(3);
            for (m, t) in self.materials.iter().zip(&terms) {
                r.push(switched_radiance(m, t, *on));
            }
            let r = [r[0].clone(), r[1].clone(), r[2].clone()];
            points.push(self.point(i as f64, SOURCE_LABELS[i].into(), &r, base, &context)?);
        }
        let r = [full[0].clone(), full[1].clone(), full[2].clone()];
        points.push(self.point(4.0, SOURCE_LABELS[4].into(), &r, base, context)?);
        Ok(points)
    }
}

/// The radiance of the terms switched on, with the texture covariance rebuilt from them by the
/// scene model's rule ([`Texture`]: `Cv` scales the reflected part, direct + skylight;
/// `Measured` scales S0). The geometry variation is not included (it is not split by source).
fn switched_radiance(m: &SceneMaterial, t: &[Stokes; 3], on: [bool; 3]) -> Radiance {
    let mut mean = Vector3::zeros();
    let mut surface = Vector3::zeros();
    for k in 0..3 {
        if on[k] {
            mean += t[k].0;
            if k < 2 {
                surface += t[k].0;
            }
        }
    }
    let cov = match m.texture {
        Texture::None => Matrix3::zeros(),
        Texture::Cv(cv) => Matrix3::from_diagonal(&surface.map(|x| (cv * x).powi(2))),
        Texture::Measured(c) => Matrix3::from_diagonal(
            &Vector3::new(c[0], c[1], c[2]).map(|x| (x * mean[0].abs()).powi(2)),
        ),
    };
    let path_relative = if on[2] && mean[0] > 0.0 {
        t[2].0.norm() / mean[0]
    } else {
        0.0
    };
    Radiance {
        mean,
        cov,
        path_relative,
        error: 0.0,
    }
}

/// `m` with its facet-slope roughness replaced; errors name `sigma` (and a vegetation target,
/// which has none).
pub(crate) fn with_sigma(m: &SceneMaterial, sigma: f64) -> Result<SceneMaterial, ModelError> {
    match m.surface {
        Surface::Microfacet { lobe, dhr } => Ok(SceneMaterial {
            surface: Surface::Microfacet {
                lobe: Microfacet::new(lobe.index(), sigma)?,
                dhr,
            },
            ..m.clone()
        }),
        Surface::Vegetation { .. } => Err(ModelError::Invalid {
            field: "sigma",
            reason: format!(
                "material {:?} uses the vegetation model, which has no roughness",
                m.name
            ),
        }),
    }
}

/// A swept value as a label: as written when short, else to four decimals.
pub(crate) fn format_value(v: f64) -> String {
    let s = format!("{v}");
    if s.len() > 8 {
        format!("{v:.4}")
    } else {
        s
    }
}
