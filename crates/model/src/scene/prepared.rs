//! The material-independent part of a scene ([`Prepared`]), computed once: the spectral nodes
//! (refined until the band-integrated direct beam and zenith sky settle), the sky's `mu` tables
//! per node, the sky irradiance, and the resolved sky.

use super::budget::*;
use super::spec::*;
use crate::air_mass::{air_mass, slant_mu0};
use crate::atmosphere::Atmosphere;
use crate::error::ModelError;
use crate::quadrature::{integrate, Tolerance};
use crate::sky::band::{
    irradiance_on_table, lagrange4_stencil, stencil_dot, table_intervals_for, BandTables,
    TABLE_MAX_INTERVALS,
};
use crate::sky::berry::BerrySky;
use crate::sky::clear::AzimuthalPhase;
use crate::sky::rayleigh::{downward_path, downward_path_beam, RayleighSky, AIR_DEPOLARIZATION};
use crate::sky::table::SkyTable;
use crate::skylight::sky_irradiance;
use crate::tiles::Field;
use nalgebra::Vector3;
use rayon::prelude::*;
use std::collections::HashMap;
use std::f64::consts::PI;
use std::sync::{Arc, Mutex, OnceLock};

/// One spectral node: centre, product-rule weight `int R E0 L_i` (W m^-2), optical depths and the
/// direct transmittance to the ground.
#[derive(Debug, Clone, Copy)]
pub(super) struct Node {
    /// The wavelength (nm); the optical depths below are its, and the model needs no more of
    /// it (tests rebuild a node's sky from it).
    #[cfg_attr(not(test), allow(dead_code))]
    pub(super) nm: f64,
    pub(super) weight: f64,
    pub(super) rayleigh: f64,
    pub(super) aerosol: f64,
    pub(super) t_sun: f64,
    /// Sky irradiance on the ground per unit weight (W m^-2 per W m^-2).
    pub(super) e_sky: f64,
}

/// Intervals of the `mu` table at first (refined while its error exceeds tol/8,
/// [`table_intervals_for`]).
pub(super) const TABLE_INTERVALS: usize = 256;

/// One spectral node's `mu` tables ([`Prepared::new`]): `A` and `B` per unit node weight at
/// `mu = j / intervals`, and their interpolation error relative to their peaks.
pub(super) struct NodeTables {
    pub(super) intervals: usize,
    pub(super) a: Vec<f64>,
    pub(super) b: Vec<f64>,
    pub(super) error: f64,
}

/// The material-independent terms of one field ray, computed once per scene and shared by
/// every material that looks along it ([`Prepared::ray_terms`]).
pub(super) struct RayTerms {
    /// Per spectral node, the node weight times the ground-to-sensor transmittance.
    pub(super) up: Vec<f64>,
    /// The direct irradiance `sum up_k t_sun,k mu0`.
    pub(super) e_dir: f64,
    /// The sky irradiance per unit `f00_diffuse`, transmitted up (the full table's, for a
    /// tabulated sky).
    pub(super) e_sky: f64,
    /// The path radiance.
    pub(super) path: Vector3<f64>,
    /// The band sky's tables for `up`, built on first use.
    pub(super) tables: OnceLock<Arc<BandTables>>,
}

/// The sky, resolved.
pub(super) enum Sky {
    SingleScattering,
    Berry(BerrySky),
    Table(TableSky),
}

/// A tabulated sky with its half-resolution copy and their irradiances per unit band weight.
pub(super) struct TableSky {
    pub(super) full: Arc<SkyTable>,
    pub(super) coarse: Option<SkyTable>,
    pub(super) e_full: f64,
    pub(super) e_coarse: f64,
}

/// The material-independent part of a scene, computed once: spectral nodes, the sky's `mu`
/// tables per node and their sky irradiances, the field geometry.
pub struct Prepared {
    pub(super) spec: SceneSpec,
    pub(super) sky: Sky,
    pub(super) atmosphere: Atmosphere,
    /// `(k0, k1)` of the Rayleigh phase `P11 = k0 (1 + c^2) + k1`, `-P12 = k0 (1 - c^2)`
    /// ([`RayleighSky::phase`]: `k0 = 3 Delta / 4`, `k1 = 1 - Delta`).
    pub(super) rayleigh_phase: [f64; 2],
    pub(super) sun: Vector3<f64>,
    pub(super) field: Field,
    pub(super) nodes: Vec<Node>,
    /// Per node: `A_k(mu_j)`, `B_k(mu_j)` ([`crate::scene`] docs), per unit node weight.
    pub(super) table_a: Vec<Vec<f64>>,
    pub(super) table_b: Vec<Vec<f64>>,
    pub(super) spectral_change: f64,
    pub(super) table_error: f64,
    /// A tabulated sky's irradiance quadrature error relative to the irradiance, when its
    /// floor let it be integrated above the tolerance (else 0: within the tolerance's budget).
    pub(super) irradiance_error: f64,
    pub(super) tol: f64,
    pub(super) evaluations: usize,
    /// [`Prepared::ray_terms`]' rays so far.
    pub(super) rays: Mutex<HashMap<[u64; 3], Arc<RayTerms>>>,
}

impl Prepared {
    /// Prepares `spec` for evaluation at relative tolerance `tol` in `[1e-10, 0.1]`. Errors
    /// name the field.
    pub fn new(spec: &SceneSpec, tol: f64) -> Result<Prepared, ModelError> {
        ModelError::check_range("tolerance", tol, 1e-10, 0.1, "[1e-10, 0.1]")?;
        spec.atmosphere.validate()?;
        let field = Field::new(&spec.pointing, spec.sun_zenith_deg, spec.sun_azimuth_deg)?;
        let sun = field.omega_sun();
        let am = air_mass(spec.sun_zenith_deg);
        let atm = spec.atmosphere;
        let build = |pairs: usize| -> Result<Vec<Node>, ModelError> {
            spec.band
                .quadratic_nodes(pairs)
                .into_iter()
                .map(|(nm, weight)| {
                    let t = atm.optical_depths(nm)?;
                    Ok(Node {
                        nm,
                        weight,
                        rayleigh: t.rayleigh,
                        aerosol: t.aerosol,
                        t_sun: (-(t.rayleigh + t.aerosol) * am).exp(),
                        e_sky: 0.0,
                    })
                })
                .collect()
        };
        // Spectral refinement on the band-integrated direct beam and zenith sky.
        let probe = |nodes: &[Node]| -> (f64, f64) {
            let direct: f64 = nodes.iter().map(|n| n.weight * n.t_sun).sum();
            let zenith: f64 = nodes
                .iter()
                .map(|n| {
                    let tau = n.rayleigh + n.aerosol;
                    n.weight * downward_path(tau, slant_mu0(sun.z), 1.0)
                })
                .sum();
            (direct, zenith)
        };
        let rel = |a: f64, b: f64| {
            if a == b {
                0.0
            } else {
                ((a - b) / b.abs().max(1e-300)).abs()
            }
        };
        let mut pairs = 1;
        let mut nodes = build(pairs)?;
        let spectral_change = loop {
            let finer = build(2 * pairs)?;
            let (a, b) = (probe(&nodes), probe(&finer));
            let change = rel(a.0, b.0).max(rel(a.1, b.1));
            nodes = finer;
            pairs *= 2;
            if change < tol / 8.0 || pairs >= 256 {
                break change;
            }
        };
        let rayleigh = RayleighSky {
            optical_depth: 0.0,
            depolarization: AIR_DEPOLARIZATION,
        };
        let mu0 = sun.z;
        let mu0_slant = slant_mu0(mu0);
        // The mu tables per unit node weight: A = tau_R / tau * path / (4 pi), B likewise with
        // ssa tau_A.
        // One node's pair as a function of `mu`, the sun beam's attenuation taken once.
        let ssa = atm.aerosol_ssa;
        let factors = |n: &Node| {
            let tau = n.rayleigh + n.aerosol;
            let lit = tau != 0.0 && mu0_slant > 0.0;
            let beam = (-tau / mu0_slant).exp();
            let (rayleigh, aerosol) = (n.rayleigh, n.aerosol);
            move |mu: f64| -> (f64, f64) {
                if !lit {
                    return (0.0, 0.0);
                }
                let path = downward_path_beam(tau, mu0_slant, mu, beam) / (4.0 * PI * tau);
                (rayleigh * path, ssa * aerosol * path)
            }
        };
        // One node's tables on `intervals` intervals (`factors` at `mu = j / intervals`; the
        // points a `previous` table on `p` intervals holds,
        // where `j p / intervals` is whole, copied from it: the same rational `mu` rounds to the
        // same `f64`, so the values are the same to the bit), and their error: a
        // half-resolution table's error at the odd points, divided by 8, relative to the
        // table's peak. Fourth-order interpolation gains 16 from halving, but the largest error
        // lies between the odd points: over 20 001 values of `mu` the rooftop's tables were off
        // by up to 1.08x the odd points' error / 16 (`sized_mu_tables_meet_their_error`).
        let node_tables = |n: &Node, intervals: usize, previous: Option<&NodeTables>| {
            let fresh = factors(n);
            let mut ta = Vec::with_capacity(intervals + 1);
            let mut tb = Vec::with_capacity(intervals + 1);
            for j in 0..=intervals {
                let (a, b) = match previous {
                    Some(p) if (j * p.intervals) % intervals == 0 => {
                        let k = j * p.intervals / intervals;
                        (p.a[k], p.b[k])
                    }
                    _ => fresh(j as f64 / intervals as f64),
                };
                ta.push(a);
                tb.push(b);
            }
            let coarse_a: Vec<f64> = ta.iter().step_by(2).copied().collect();
            let coarse_b: Vec<f64> = tb.iter().step_by(2).copied().collect();
            let peak = |t: &[f64]| t.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let (peak_a, peak_b) = (peak(&ta), peak(&tb));
            let mut error = 0.0f64;
            for j in (1..intervals).step_by(2) {
                let (i, w) = lagrange4_stencil(coarse_a.len(), j as f64 / intervals as f64);
                for (coarse, t, peak) in [(&coarse_a, &ta, peak_a), (&coarse_b, &tb, peak_b)] {
                    if peak > 0.0 {
                        let e = (stencil_dot(&w, &coarse[i - 1..i + 3]) - t[j]).abs() / 8.0 / peak;
                        error = error.max(e);
                    }
                }
            }
            NodeTables {
                intervals,
                a: ta,
                b: tb,
                error,
            }
        };
        // The tables: 256 intervals, refined until their error is below tol/8. The nodes are
        // independent: built in parallel, collected in their order (the result does not depend
        // on the thread count).
        let build_tables = |nodes: &[Node], intervals: usize, previous: &[Option<NodeTables>]| {
            nodes
                .par_iter()
                .enumerate()
                .map(|(k, n)| node_tables(n, intervals, previous.get(k).and_then(Option::as_ref)))
                .collect::<Vec<NodeTables>>()
        };
        // From 256 intervals on, the table's error falls as the fourth power of the interval
        // (fourth-order interpolation; measured on the rooftop: a factor 4 in intervals gives
        // about 230x, against 4^4 = 256, while below 256 intervals the error falls more slowly):
        // a table short of tol/8 is rebuilt at the size that law asks for with a
        // factor 2 to spare, and checked again. The first size is probed on the nodes of least
        // and greatest optical depth alone, where the error is largest (the horizon's
        // transition lies at `mu ~ tau`: sharpest for the least, and the greatest has the
        // deepest attenuation), and every node's tables are built at the size their error asks
        // for and checked there; were another node's error larger, the check refines again.
        let mut intervals = TABLE_INTERVALS;
        let tau = |k: usize| nodes[k].rayleigh + nodes[k].aerosol;
        let by_tau = |a: &usize, b: &usize| tau(*a).total_cmp(&tau(*b));
        let mut probes: Vec<usize> = [
            (0..nodes.len()).min_by(by_tau),
            (0..nodes.len()).max_by(by_tau),
        ]
        .into_iter()
        .flatten()
        .collect();
        probes.dedup();
        let mut previous: Vec<Option<NodeTables>> = (0..nodes.len()).map(|_| None).collect();
        let probed: Vec<NodeTables> = probes
            .par_iter()
            .map(|&k| node_tables(&nodes[k], intervals, None))
            .collect();
        let probe_error = probed.iter().fold(0.0f64, |m, t| m.max(t.error));
        if probe_error > tol / 8.0 {
            intervals = table_intervals_for(intervals, probe_error, tol / 8.0);
        }
        for (k, t) in probes.into_iter().zip(probed) {
            previous[k] = Some(t);
        }
        let (tables, table_error) = loop {
            let tables = build_tables(&nodes, intervals, &previous);
            let error = tables.iter().fold(0.0f64, |m, t| m.max(t.error));
            if error <= tol / 8.0 || intervals >= TABLE_MAX_INTERVALS {
                break (tables, error);
            }
            intervals = table_intervals_for(intervals, error, tol / 8.0);
            previous = tables.into_iter().map(Some).collect();
        };
        // Sky irradiance per unit weight, `int_0^1 mu (P_R(mu) A(mu) + P_HG(mu) B(mu)) dmu` with
        // the phase functions integrated over azimuth in closed form: by Simpson's rule on the
        // tables' points, where `A` and `B` are already known and the phase functions, the same
        // for every node, are evaluated once (`irradiance_on_table`); a node whose rule does
        // not meet tol/64 of its zenith radiance is integrated adaptively instead.
        let phase = AzimuthalPhase::new(&rayleigh, atm.aerosol_g, mu0);
        let phases = phase.on_grid(intervals);
        // Simpson's rule where it resolves the HG term's peak ([`AzimuthalPhase::resolves`]);
        // the adaptive rule on pieces graded towards it ([`AzimuthalPhase::breaks`]).
        let on_grid = phase.resolves(intervals);
        let breaks = phase.breaks(4.0);
        let irradiances: Vec<(f64, usize)> = nodes
            .par_iter()
            .zip(&tables)
            .map(|(n, t)| {
                let scale = t.a[intervals].max(t.b[intervals]).max(1e-300);
                let target = tol / 64.0 * scale;
                if let Some((e, error)) = irradiance_on_table(&phases, &t.a, &t.b) {
                    if on_grid && error <= target {
                        return (e, 0);
                    }
                }
                let factors = factors(n);
                let f = |mu: f64| {
                    let (fa, fb) = factors(mu);
                    let hg = if fb == 0.0 { 0.0 } else { phase.hg(mu) };
                    mu * (phase.rayleigh(mu) * fa + hg * fb)
                };
                let pieces = (breaks.len() - 1) as f64;
                breaks
                    .windows(2)
                    .fold((0.0, 0), |(value, evaluations), ab| {
                        let e = integrate(f, ab[0], ab[1], Tolerance::absolute(target / pieces));
                        (value + e.value, evaluations + e.evaluations)
                    })
            })
            .collect();
        let mut evaluations = phases.len();
        for (n, (e_sky, e)) in nodes.iter_mut().zip(irradiances) {
            n.e_sky = e_sky;
            evaluations += e;
        }
        let (table_a, table_b): (Vec<Vec<f64>>, Vec<Vec<f64>>) =
            tables.into_iter().map(|t| (t.a, t.b)).unzip();
        let mut irradiance_error = 0.0;
        let sky = match &spec.sky {
            SkyModel::SingleScattering => Sky::SingleScattering,
            SkyModel::Berry {
                separation_deg,
                max_dolp,
            } => {
                let sep = ModelError::check_range(
                    "sky.separation_deg",
                    *separation_deg,
                    0.0,
                    60.0,
                    "[0, 60]",
                )?;
                let d = ModelError::check_range("sky.max_dolp", *max_dolp, 0.0, 1.0, "[0, 1]")?;
                let b = BerrySky {
                    sun,
                    separation_rad: sep.to_radians(),
                    max_dolp: d,
                };
                Sky::Berry(b)
            }
            SkyModel::Table(t) => {
                // The table replaces the sky: its irradiance, per unit band weight, on every node.
                // The table's own irradiance floor first: the full and half-resolution tables'
                // irradiances at a loose tolerance, the change halved plus their quadrature
                // errors. Integrating further than a quarter of it buys nothing (the module
                // docs, "Error floors"): only a tolerance above that is met, and the irradiance's
                // quadrature error is then carried in `irradiance_error`.
                let w: f64 = nodes.iter().map(|n| n.weight).sum();
                let peak = t.peak_radiance().max(1e-300);
                let coarse = t.half_resolution();
                let both = |tol_rel: f64| {
                    let tol_e = Tolerance::absolute(tol_rel / 64.0 * peak);
                    let e = sky_irradiance(t.as_ref(), tol_e);
                    let c = coarse.as_ref().map(|c| sky_irradiance(c, tol_e));
                    (e, c)
                };
                let loose = tol.max(FLOOR_PROBE_TOL);
                let (mut e, mut c) = both(loose);
                evaluations += e.evaluations + c.as_ref().map_or(0, |c| c.evaluations);
                let tol_e = match &c {
                    Some(c) => {
                        let change = (e.stokes.0[0] - c.stokes.0[0]).abs() + e.error + c.error;
                        tol.max(FLOOR_FRACTION * change / 2.0 / e.stokes.0[0].abs().max(1e-300))
                    }
                    None => tol,
                };
                if tol_e < loose {
                    (e, c) = both(tol_e);
                    evaluations += e.evaluations + c.as_ref().map_or(0, |c| c.evaluations);
                }
                if tol_e > tol {
                    irradiance_error = e.error / e.stokes.0[0].abs().max(1e-300);
                }
                let e_coarse = c.map_or(e.stokes.0[0], |c| c.stokes.0[0]);
                for n in &mut nodes {
                    n.e_sky = e.stokes.0[0] / w;
                }
                Sky::Table(TableSky {
                    full: Arc::clone(t),
                    coarse,
                    e_full: e.stokes.0[0] / w,
                    e_coarse: e_coarse / w,
                })
            }
        };
        Ok(Prepared {
            spec: spec.clone(),
            sky,
            atmosphere: atm,
            rayleigh_phase: {
                let (p11, p12) = rayleigh.phase(0.0);
                [p12, p11 - p12]
            },
            sun,
            field,
            nodes,
            table_a,
            table_b,
            spectral_change,
            table_error,
            irradiance_error,
            tol,
            evaluations,
            rays: Mutex::new(HashMap::new()),
        })
    }
}
