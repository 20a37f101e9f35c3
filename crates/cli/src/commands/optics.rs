//! The optics of one surface and one polarimeter: Fresnel (`model fresnel`), the polarimetric
//! BRDF (`model pbrdf`), the Stokes estimate from analyzer intensities (`model stokes`) and an
//! analyzer set's conditioning (`model polarimeter`).

use super::args::{deg_to_rad, required};
use super::error::CommandError;
use super::text::{compact, echo};
use clap::Args;
use polar_model::analyzer::{AnalyzerModel, AnalyzerSet};
use polar_model::fresnel::{amplitudes, RefractiveIndex};
use polar_model::material::{MaterialLibrary, MaterialModel};
use polar_model::pbrdf::{DiffuseTerm, Geometry, Surface};
use polar_model::quadrature::Tolerance;
use polar_model::ModelError;
use serde::Deserialize;
use serde_json::{json, Value};
use std::collections::HashMap;

/// `polarimeter model fresnel`: Fresnel amplitudes and reflectances at one angle.
#[derive(Debug, Clone, Default, Args, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FresnelArgs {
    /// Real part of the refractive index, (0, 100].
    #[arg(long)]
    pub n: Option<f64>,
    /// Extinction coefficient, [0, 100] (0 for a dielectric).
    #[arg(long, default_value_t = 0.0)]
    #[serde(default)]
    pub k: f64,
    /// Angle of incidence from the normal, degrees, [0, 90].
    #[arg(long)]
    pub theta_i_deg: Option<f64>,
}

/// Evaluates [`FresnelArgs`].
pub fn fresnel(a: &FresnelArgs) -> Result<Value, CommandError> {
    let idx = RefractiveIndex::new(required(a.n, "n", "(0, 100]")?, a.k)?;
    let ti = deg_to_rad(
        "theta_i_deg",
        required(a.theta_i_deg, "theta_i_deg", "[0, 90]")?,
        0.0,
        90.0,
        "[0, 90]",
    )?;
    let r = amplitudes(&idx, ti)?;
    let mut out = json!({
        "rs": [r.rs.re, r.rs.im],
        "rp": [r.rp.re, r.rp.im],
        "Rs": r.rs_power(),
        "Rp": r.rp_power(),
        "re_rs_rp_conj": r.re_rs_rp_conj(),
    });
    if idx.k > 0.0 {
        // An absorbing medium has no Brewster angle (Rp never vanishes): the pseudo-Brewster
        // angle, where Rp is smallest, and that Rp.
        let pb = idx.pseudo_brewster();
        out["pseudo_brewster_deg"] = json!(pb.angle_rad.to_degrees());
        out["rp_min"] = json!(pb.rp_min);
    } else {
        out["brewster_deg"] = json!(idx.brewster_angle_rad().to_degrees());
    }
    Ok(out)
}

/// `polarimeter model pbrdf`: the full pBRDF Mueller matrix at one geometry.
#[derive(Debug, Clone, Args, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PbrdfArgs {
    /// Real part of the refractive index, (0, 100].
    #[arg(long)]
    pub n: Option<f64>,
    /// Extinction coefficient, [0, 100] (default 0, or the material's).
    #[arg(long)]
    #[serde(default)]
    pub k: Option<f64>,
    /// A built-in material (glass, black_paint, asphalt, vegetation, aluminium, copper, gold,
    /// silver; see `polarimeter model materials`) supplying n, k, sigma, dhr and the model;
    /// explicit flags override its values.
    #[arg(long)]
    #[serde(default)]
    pub material: Option<String>,
    /// Facet-slope roughness sigma_h / l, [1e-6, 10] (not used with --vegetation).
    #[arg(long)]
    pub sigma: Option<f64>,
    /// Directional-hemispherical reflectance, [0, 1]. With --vegetation the diffuse term is dhr/pi
    /// (Meng (2012)'s vegetation: --n 1.5 --dhr 0.04).
    #[arg(long)]
    pub dhr: Option<f64>,
    /// Incident (sun) zenith angle, degrees, [0, 90].
    #[arg(long)]
    pub theta_i_deg: Option<f64>,
    /// View zenith angle, degrees, [0, 90].
    #[arg(long)]
    pub theta_r_deg: Option<f64>,
    /// Relative azimuth between source and view directions, degrees, [-360, 360]; 180 is specular.
    #[arg(long)]
    pub phi_deg: Option<f64>,
    /// Use the vegetation model (Meng (2012) Eq. 3.19) instead of the microfacet model.
    #[arg(long)]
    #[serde(default)]
    pub vegetation: bool,
    /// Absolute error target of the specular-albedo quadrature, [1e-14, 1e-2].
    #[arg(long, default_value_t = 1e-9)]
    #[serde(default = "default_tolerance")]
    pub tolerance: f64,
}

fn default_tolerance() -> f64 {
    1e-9
}

impl PbrdfArgs {
    /// Fills unset parameters from `--material` (explicit flags win).
    pub fn resolved(&self) -> Result<PbrdfArgs, CommandError> {
        let Some(name) = &self.material else {
            return Ok(self.clone());
        };
        let lib = MaterialLibrary::builtin();
        let m = lib
            .get(name)
            .map_err(|e| CommandError::input("material", format!(": {e}")))?;
        let vegetation = self.vegetation || m.model == MaterialModel::Vegetation;
        Ok(PbrdfArgs {
            n: self.n.or(Some(m.n)),
            k: self.k.or(Some(m.k)),
            sigma: self.sigma.or(m.sigma),
            // The vegetation model's diffuse term is dhr / pi.
            dhr: self
                .dhr
                .or(m.dhr)
                .or(m.f00_diffuse.map(|f| f * std::f64::consts::PI)),
            vegetation,
            material: None,
            ..self.clone()
        })
    }

    /// The surface these (resolved) parameters describe.
    pub fn surface(&self) -> Result<Surface, CommandError> {
        let idx = RefractiveIndex::new(required(self.n, "n", "(0, 100]")?, self.k.unwrap_or(0.0))?;
        let dhr = required(self.dhr, "dhr", "[0, 1]")?;
        if self.vegetation {
            ModelError::check_range("dhr", dhr, 0.0, 1.0, "[0, 1]")?;
            Ok(Surface::vegetation(idx, dhr / std::f64::consts::PI)?)
        } else {
            Ok(Surface::microfacet(
                idx,
                required(self.sigma, "sigma", "[1e-6, 10]")?,
                dhr,
            )?)
        }
    }
}

/// Caches diffuse terms across evaluations that share material and incidence angle (a batch of
/// view directions under one sun integrates the specular albedo once).
#[derive(Debug, Default)]
pub struct DiffuseCache {
    map: HashMap<[u64; 6], DiffuseTerm>,
}

impl DiffuseCache {
    /// Number of distinct diffuse terms computed.
    pub fn len(&self) -> usize {
        self.map.len()
    }

    /// Whether nothing has been cached yet.
    pub fn is_empty(&self) -> bool {
        self.map.is_empty()
    }
}

/// Evaluates [`PbrdfArgs`], reusing diffuse terms from `cache`.
pub fn pbrdf(a: &PbrdfArgs, cache: &mut DiffuseCache) -> Result<Value, CommandError> {
    let a = &a.resolved()?;
    let surface = a.surface()?;
    let ti = required(a.theta_i_deg, "theta_i_deg", "[0, 90]")?;
    let tr = required(a.theta_r_deg, "theta_r_deg", "[0, 90]")?;
    let phi = required(a.phi_deg, "phi_deg", "[-360, 360]")?;
    let g = Geometry::from_deg(ti, tr, phi)?;
    let tol = ModelError::check_range("tolerance", a.tolerance, 1e-14, 1e-2, "[1e-14, 1e-2]")?;
    let key = [
        a.n.unwrap_or(0.0).to_bits(),
        a.k.unwrap_or(0.0).to_bits(),
        if a.vegetation {
            u64::MAX
        } else {
            a.sigma.unwrap_or(0.0).to_bits()
        },
        a.dhr.unwrap_or(0.0).to_bits(),
        ti.to_bits(),
        tol.to_bits(),
    ];
    let diffuse = match cache.map.get(&key) {
        Some(d) => *d,
        None => {
            let d = surface.diffuse(ti.to_radians(), Tolerance::absolute(tol))?;
            cache.map.insert(key, d);
            d
        }
    };
    let f = surface.mueller_with(&g, &diffuse);
    let out = f.response_to_unpolarized();
    let warnings = diffuse_warnings(&diffuse, tol);
    let m = f.0;
    Ok(json!({
        "f": [[m[(0, 0)], m[(0, 1)], m[(0, 2)]], [m[(1, 0)], m[(1, 1)], m[(1, 2)]], [m[(2, 0)], m[(2, 1)], m[(2, 2)]]],
        "dolp": out.dolp().unwrap_or(0.0),
        "aop_deg": out.aop_rad().map(f64::to_degrees),
        "f00_diffuse": diffuse.f00,
        "specular_albedo": diffuse.specular_albedo.value,
        "specular_albedo_error": diffuse.specular_albedo.error,
        "quadrature_evaluations": diffuse.specular_albedo.evaluations,
        "warnings": warnings,
    }))
}

/// What a diffuse term warns of: a clamped albedo product, a specular-albedo quadrature short
/// of its tolerance `tol`.
pub fn diffuse_warnings(diffuse: &DiffuseTerm, tol: f64) -> Vec<String> {
    let mut warnings = Vec::new();
    if let Some(w) = diffuse.clamped {
        warnings.push(w.to_string());
    }
    if !diffuse.specular_albedo.converged {
        warnings.push(format!(
            "specular albedo quadrature did not reach tolerance {tol:e}: error estimate {:e}",
            diffuse.specular_albedo.error
        ));
    }
    warnings
}

/// `polarimeter model stokes`: least-squares Stokes reconstruction from analyzer intensities.
#[derive(Debug, Clone, Default, Args, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StokesArgs {
    /// Analyzer angles, degrees, comma-separated; at least 3 distinct modulo 180.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    #[serde(default)]
    pub angles_deg: Vec<f64>,
    /// Measured intensities, one per angle, comma-separated.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    #[serde(default)]
    pub intensities: Vec<f64>,
}

pub(super) fn analyzer_set(
    angles_deg: &[f64],
    model: &AnalyzerModel,
) -> Result<AnalyzerSet, CommandError> {
    if let Some(bad) = angles_deg
        .iter()
        .find(|a| !a.is_finite() || a.abs() > 3600.0)
    {
        return Err(CommandError::input(
            "angles_deg",
            format!(
                " contains {}: allowed finite values in [-3600, 3600]",
                compact(*bad)
            ),
        ));
    }
    let rad: Vec<f64> = angles_deg.iter().map(|a| a.to_radians()).collect();
    Ok(AnalyzerSet::new(&rad, model)?)
}

/// Evaluates [`StokesArgs`]. Intensities are powers: a negative one (noise after a dark is
/// subtracted) is a warning, and a fit without light (S0 <= 0) is refused.
pub fn stokes(a: &StokesArgs) -> Result<Value, CommandError> {
    let set = analyzer_set(&a.angles_deg, &AnalyzerModel::IDEAL)?;
    if let Some((i, v)) = a
        .intensities
        .iter()
        .enumerate()
        .find(|(_, v)| !v.is_finite())
    {
        return Err(CommandError::input(
            format!("intensities[{i}]"),
            format!(
                " = {} is out of range: allowed finite values >= 0",
                compact(*v)
            ),
        ));
    }
    let s = set.reconstruct(&a.intensities)?;
    if s.0[0].is_nan() || s.0[0] <= 0.0 {
        let list: Vec<String> = a.intensities.iter().map(|v| compact(*v)).collect();
        return Err(CommandError::input(
            "intensities",
            format!(
                " = {} give S0 = {}: allowed values >= 0 (measured powers) whose fit \
             has S0 > 0",
                echo(&list.join(",")),
                compact(s.0[0])
            ),
        ));
    }
    let warnings: Vec<String> = a
        .intensities
        .iter()
        .enumerate()
        .filter(|(_, v)| **v < 0.0)
        .map(|(i, v)| {
            format!(
                "intensities[{i}] = {} is negative: allowed >= 0 (kept as noise; a dark \
                 subtracted twice?)",
                compact(*v)
            )
        })
        .collect();
    let predicted = set.intensities(&s);
    let n = a.intensities.len() as f64;
    let rss: f64 = predicted
        .iter()
        .zip(&a.intensities)
        .map(|(p, i)| (p - i).powi(2))
        .sum();
    Ok(json!({
        "s": [s.0[0], s.0[1], s.0[2]],
        "dolp": s.dolp(),
        "aop_deg": s.aop_rad().map(f64::to_degrees),
        "residual_rms": (rss / n).sqrt(),
        "warnings": warnings,
    }))
}

/// `polarimeter model polarimeter`: conditioning and noise gains of an analyzer set.
#[derive(Debug, Clone, Args, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PolarimeterArgs {
    /// Analyzer angles, degrees, comma-separated; at least 3 distinct modulo 180.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    #[serde(default)]
    pub angles_deg: Vec<f64>,
    /// Analyzer extinction ratio k1/k2, > 1 (inf: ideal).
    #[arg(long, default_value_t = f64::INFINITY)]
    #[serde(default = "infinite")]
    pub extinction_ratio: f64,
    /// Analyzer angle offset added to every angle, degrees, [-180, 180].
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    #[serde(default)]
    pub offset_deg: f64,
}

fn infinite() -> f64 {
    f64::INFINITY
}

/// Evaluates [`PolarimeterArgs`].
pub fn polarimeter(a: &PolarimeterArgs) -> Result<Value, CommandError> {
    ModelError::check_range("offset_deg", a.offset_deg, -180.0, 180.0, "[-180, 180]")?;
    let model =
        AnalyzerModel::from_extinction_ratio(a.extinction_ratio, a.offset_deg.to_radians())?;
    let set = analyzer_set(&a.angles_deg, &model)?;
    let rows = |m: &nalgebra::DMatrix<f64>| -> Vec<Vec<f64>> {
        (0..m.nrows())
            .map(|i| m.row(i).iter().copied().collect())
            .collect()
    };
    Ok(json!({
        "cond2": set.cond2(),
        "ewv": set.ewv(),
        "singular_values": set.singular_values(),
        "pinv": rows(set.stokes_from_intensities()),
        "w": rows(set.intensities_from_stokes()),
        "noise_gains": set.noise_gains(),
    }))
}
