//! `polarimeter plan angles`: the SCR-optimal analyzer set for a target against a background
//! (MODEL.md section 9), with the conventional sets beside it; and `polarimeter bench planner`:
//! the optimiser against an exhaustive grid, in the same run.

use crate::commands::CommandError;
use crate::plan_problem::planner_error;
use clap::Args;
use nalgebra::{Matrix3, Vector3};
use polar_planner::optimize::{grid_search, MAX_CHANNELS};
use polar_planner::stokes::STOKES_MAX_CONDITION;
use polar_planner::{conventional, optimise, Constraints, Contrast, Optimum};
use serde_json::{json, Value};
use std::time::{Duration, Instant};

/// `plan angles` arguments.
#[derive(Debug, Clone, Args)]
pub struct PlanAnglesArgs {
    /// Channels (analyzer angles), 1..=6.
    #[arg(long, default_value_t = 3)]
    pub channels: usize,
    /// Target Stokes mean S0,S1,S2 (any unit; the same as the noise variance's square root).
    #[arg(
        long,
        value_delimiter = ',',
        allow_hyphen_values = true,
        required = true
    )]
    pub target_mean: Vec<f64>,
    /// Background Stokes mean S0,S1,S2.
    #[arg(
        long,
        value_delimiter = ',',
        allow_hyphen_values = true,
        required = true
    )]
    pub background_mean: Vec<f64>,
    /// Background Stokes covariance, 9 values row-major.
    #[arg(
        long,
        value_delimiter = ',',
        allow_hyphen_values = true,
        required = true
    )]
    pub background_cov: Vec<f64>,
    /// Per-frame sensor noise variance V, in the unit of the means squared, >= 0.
    #[arg(long)]
    pub noise_var: f64,
    /// Target Stokes covariance, 9 values row-major (default: the background's); used for Pd.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub target_cov: Option<Vec<f64>>,
    /// A filter wheel's fixed polarizer angles, degrees: choose the best subset.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub fixed_angles_deg: Option<Vec<f64>>,
    /// Smallest separation between two angles, degrees, [0, 90).
    #[arg(long, default_value_t = 0.0)]
    pub min_separation_deg: f64,
    /// A rotator's travel LO,HI, degrees (hi - lo < 180).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub angle_range_deg: Option<Vec<f64>>,
    /// The stage's smallest step, degrees (0: continuous).
    #[arg(long, default_value_t = 0.0)]
    pub step_deg: f64,
    /// Angle tolerance of the optimum, degrees.
    #[arg(long, default_value_t = 0.01)]
    pub tolerance_deg: f64,
    /// False-alarm rate for the Pd figures, (0, 1).
    #[arg(long, default_value_t = 1e-3)]
    pub pfa: f64,
    /// The detection-only optimum: the SCR-optimal set whatever it forms (repeated angles and
    /// 1 or 2 channels allowed), with no Stokes image; by default the set forms a Stokes image,
    /// as in `plan scene` (3 or more angles whose ideal measurement matrix has a condition
    /// number of at most 6.21, that of 0/30/60).
    #[arg(long)]
    pub detection_only: bool,
}

fn vec3(field: &str, v: &[f64]) -> Result<Vector3<f64>, CommandError> {
    match v {
        [a, b, c] => Ok(Vector3::new(*a, *b, *c)),
        _ => Err(CommandError::input(
            field,
            format!(" has {} values: allowed 3 (S0,S1,S2)", v.len()),
        )),
    }
}

fn mat3(field: &str, v: &[f64]) -> Result<Matrix3<f64>, CommandError> {
    if v.len() != 9 {
        return Err(CommandError::input(
            field,
            format!(" has {} values: allowed 9 (3x3 row-major)", v.len()),
        ));
    }
    Ok(Matrix3::from_row_slice(v))
}

/// The matched filter's ROC of the set at `pfa` ([`polar_planner::scr::matched_filter_roc`]).
pub(crate) fn intensity_roc(
    angles_rad: &[f64],
    t_mean: &Vector3<f64>,
    t_cov: &Matrix3<f64>,
    b_mean: &Vector3<f64>,
    b_cov: &Matrix3<f64>,
    noise_var: f64,
    pfa: f64,
) -> Result<polar_model::metrics::Roc, CommandError> {
    Ok(polar_planner::scr::matched_filter_roc(
        angles_rad,
        (t_mean, t_cov),
        (b_mean, b_cov),
        noise_var,
        pfa,
    )?)
}

/// `plan angles`.
pub fn angles(args: &PlanAnglesArgs) -> Result<Value, CommandError> {
    if !(1..=MAX_CHANNELS).contains(&args.channels) {
        return Err(CommandError::input(
            "channels",
            format!(
                " = {} is out of range: allowed 1 to {MAX_CHANNELS}",
                args.channels
            ),
        ));
    }
    let stokes = !args.detection_only;
    if stokes && args.channels < 3 {
        return Err(CommandError::input(
            "--channels",
            format!(
                " {} is out of range for a Stokes set: allowed 3 to {MAX_CHANNELS} (a \
             linear Stokes vector has 3 unknowns), or add --detection-only for 1 or 2 channels",
                args.channels
            ),
        ));
    }
    let t_mean = vec3("target_mean", &args.target_mean)?;
    let b_mean = vec3("background_mean", &args.background_mean)?;
    let b_cov = mat3("background_cov", &args.background_cov)?;
    let t_cov = match &args.target_cov {
        Some(v) => mat3("target_cov", v)?,
        None => b_cov,
    };
    let contrast = Contrast::new(t_mean - b_mean, b_cov, args.noise_var).map_err(planner_error)?;
    let range_rad = match &args.angle_range_deg {
        None => None,
        Some(v) if v.len() == 2 => Some((v[0].to_radians(), v[1].to_radians())),
        Some(v) => {
            return Err(CommandError::input(
                "angle_range_deg",
                format!(" has {} values: allowed 2 (LO,HI)", v.len()),
            ))
        }
    };
    let constraints = Constraints {
        range_rad,
        min_separation_rad: args.min_separation_deg.to_radians(),
        step_rad: args.step_deg.to_radians(),
        fixed_angles_rad: args
            .fixed_angles_deg
            .as_ref()
            .map(|v| v.iter().map(|d| d.to_radians()).collect()),
        max_condition: stokes.then_some(STOKES_MAX_CONDITION),
    };
    let t0 = Instant::now();
    let opt = optimise(
        &contrast,
        args.channels,
        &constraints,
        args.tolerance_deg.to_radians(),
    )
    .map_err(planner_error)?;
    let elapsed_ms = t0.elapsed().as_secs_f64() * 1e3;
    let pd_of = |a: &[f64]| {
        intensity_roc(
            a,
            &t_mean,
            &t_cov,
            &b_mean,
            &b_cov,
            contrast.noise_var,
            args.pfa,
        )
        .map(|r| r.pd)
    };
    let mut scr_conv = serde_json::Map::new();
    let mut pd_conv = serde_json::Map::new();
    for (name, scr) in conventional(&contrast) {
        let rad: Vec<f64> = name
            .split('/')
            .filter_map(|d| d.parse::<f64>().ok())
            .map(f64::to_radians)
            .collect();
        scr_conv.insert(name.into(), json!(scr));
        pd_conv.insert(name.into(), json!(pd_of(&rad)?));
    }
    let limit = contrast.clutter_limit();
    let mut notes = contrast.notes.clone();
    let distinct = {
        let mut a: Vec<f64> = opt.angles_rad.clone();
        a.sort_by(f64::total_cmp);
        a.dedup_by(|x, y| (*x - *y).abs() < 1e-9);
        a.len()
    };
    if !stokes && distinct < 3 {
        notes.push(format!(
            "detection only: the set has {distinct} distinct angle(s); it detects in the \
             intensity frames but forms no Stokes image"
        ));
    }
    let ideal_condition = polar_planner::stokes::stokes_condition(&opt.angles_rad);
    let set = json!({
        "kind": if stokes { "stokes" } else { "detection-only" },
        "rule": if stokes {
            format!(
                "{} angles whose ideal measurement matrix has a condition number of at most \
                 {STOKES_MAX_CONDITION} (that of 0/30/60, the worst 3-angle set 30 deg apart)",
                args.channels
            )
        } else {
            format!("{} angles, repeats allowed: {distinct} distinct angle(s)", args.channels)
        },
        "condition_number_ideal": if ideal_condition.is_finite() { json!(ideal_condition) } else { Value::Null },
    });
    Ok(json!({
        "angles_deg": opt.angles_rad.iter().map(|a| a.to_degrees()).collect::<Vec<_>>(),
        "set": set,
        "scr": opt.scr,
        "pd": pd_of(&opt.angles_rad)?,
        "pfa": args.pfa,
        "scr_conventional": scr_conv,
        "pd_conventional": pd_conv,
        "scr_clutter_limit": if limit.is_finite() { json!(limit) } else { Value::Null },
        "clutter_condition": if contrast.clutter_condition.is_finite() { json!(contrast.clutter_condition) } else { Value::Null },
        "evaluations": opt.evaluations,
        "elapsed_ms": elapsed_ms,
        "notes": notes,
    }))
}

/// One row of `bench planner`.
#[derive(Debug, Clone)]
pub struct PlannerRow {
    /// Channels.
    pub channels: usize,
    /// The optimiser: median time and its answer.
    pub ours: (Duration, Optimum),
    /// The exhaustive 1-degree grid: time and its answer.
    pub grid: (Duration, Optimum),
}

/// A fixed benchmark problem: correlated clutter where the angles matter (a glass-like target,
/// DoLP 0.3, against asphalt-like clutter; noise comparable to the clutter).
pub fn bench_problem() -> Result<Contrast, CommandError> {
    let b_cov = Matrix3::new(400.0, 30.0, -20.0, 30.0, 60.0, 12.0, -20.0, 12.0, 45.0);
    Contrast::new(Vector3::new(40.0, 30.0, -12.0), b_cov, 80.0).map_err(planner_error)
}

/// Runs the optimiser (to 0.01 deg) `runs` times per N (median) and the exhaustive 1-degree
/// grid once, for N = 1..=max_n.
pub fn bench(max_n: usize, runs: usize) -> Result<Vec<PlannerRow>, CommandError> {
    let contrast = bench_problem()?;
    let mut rows = Vec::new();
    for n in 1..=max_n.min(MAX_CHANNELS) {
        let mut times = Vec::new();
        let mut answer = None;
        for _ in 0..runs.max(1) {
            let t0 = Instant::now();
            let opt = optimise(&contrast, n, &Constraints::default(), 0.01f64.to_radians())
                .map_err(planner_error)?;
            times.push(t0.elapsed());
            answer = Some(opt);
        }
        times.sort();
        let ours = (
            times[times.len() / 2],
            answer.ok_or_else(|| CommandError::failed("no run"))?,
        );
        let t0 = Instant::now();
        let grid = grid_search(&contrast, n, 1f64.to_radians());
        rows.push(PlannerRow {
            channels: n,
            ours,
            grid: (t0.elapsed(), grid),
        });
    }
    Ok(rows)
}

/// The rows as a Markdown table.
pub fn markdown(rows: &[PlannerRow]) -> String {
    let time = |d: Duration| {
        let us = d.as_secs_f64() * 1e6;
        if us < 1000.0 {
            format!("{us:.1} us")
        } else {
            format!("{:.2} ms", us / 1e3)
        }
    };
    let deg = |a: &[f64]| {
        a.iter()
            .map(|v| format!("{:.2}", v.to_degrees()))
            .collect::<Vec<_>>()
            .join("/")
    };
    let mut out = String::from(
        "| N | optimiser (0.01 deg) | its SCR | angles, deg | 1-deg grid | grid SCR | grid evaluations | speed-up | SCR ours / grid |\n|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        out.push_str(&format!(
            "| {} | {} | {:.6} | {} | {} | {:.6} | {} | {:.1}x | {:.9} |\n",
            r.channels,
            time(r.ours.0),
            r.ours.1.scr,
            deg(&r.ours.1.angles_rad),
            time(r.grid.0),
            r.grid.1.scr,
            r.grid.1.evaluations,
            r.grid.0.as_secs_f64() / r.ours.0.as_secs_f64().max(1e-12),
            r.ours.1.scr / r.grid.1.scr,
        ));
    }
    out
}

/// `analyze aptd --frames DIR`: APTD offline over an image stack.
#[derive(Debug, Clone, Args)]
pub struct PlanAptdArgs {
    /// The stack: `frames.csv` (`file,angle_deg`) and the 16-bit TIFFs it names.
    #[arg(long)]
    pub frames: std::path::PathBuf,
    /// Per-frame sensor noise variance, DN^2 (from the calibrated camera), >= 0.
    #[arg(long)]
    pub noise_var: f64,
    /// Black level subtracted from every pixel, DN.
    #[arg(long, default_value_t = 0.0)]
    pub dark_dn: f64,
    /// Channels per set, 1..=6.
    #[arg(long, default_value_t = 3)]
    pub channels: usize,
    /// The first set, degrees (angles of the stack).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, default_values_t = [0.0, 60.0, 120.0])]
    pub initial_angles_deg: Vec<f64>,
    /// A known target region X0,Y0,X1,Y1 (pixels, end exclusive).
    #[arg(long, value_delimiter = ',')]
    pub target_region: Option<Vec<u32>>,
    /// Otherwise: this fraction of pixels with the highest RX score, (0, 0.5).
    #[arg(long, default_value_t = 0.01)]
    pub anomalies: f64,
    /// Frames the loop may use, first set included.
    #[arg(long, default_value_t = 15)]
    pub frame_budget: usize,
    /// False-alarm rate of the empirical Pd, (0, 1).
    #[arg(long, default_value_t = 1e-3)]
    pub pfa: f64,
}

/// The frames of a stack's `frames.csv`, by its header: the `file` column and the angle in
/// `angle_deg` (a stack written by hand) or `commanded_angle_deg` (an `acquire export tiff`,
/// whose measured angles sit within the driver's readback tolerance of it). In an export,
/// dark frames (`kind` = dark) and frames that do not count (`accepted` = false) are left out.
fn read_stack_list(
    list: &std::path::Path,
    text: &str,
) -> Result<Vec<(f64, std::path::PathBuf)>, CommandError> {
    let dir = list.parent().unwrap_or(std::path::Path::new("."));
    let mut lines = text.lines().enumerate();
    let header: Vec<&str> = lines
        .next()
        .map(|(_, h)| h.split(',').map(str::trim).collect())
        .unwrap_or_default();
    let col = |name: &str| header.iter().position(|h| *h == name);
    let (Some(file_col), Some(angle_col)) = (
        col("file"),
        col("angle_deg").or_else(|| col("commanded_angle_deg")),
    ) else {
        return Err(CommandError::failed(format!(
            "{}: the header {:?} lacks a column: allowed file and angle_deg (or an export's \
             file and commanded_angle_deg)",
            list.display(),
            header.join(",")
        )));
    };
    let (kind_col, accepted_col) = (col("kind"), col("accepted"));
    let mut stack = Vec::new();
    for (i, line) in lines {
        if line.trim().is_empty() {
            continue;
        }
        let cols: Vec<&str> = line.split(',').map(str::trim).collect();
        let cell = |c: usize| cols.get(c).copied();
        if kind_col.and_then(cell) == Some("dark") || accepted_col.and_then(cell) == Some("false") {
            continue;
        }
        let (Some(file), Some(angle)) = (cell(file_col), cell(angle_col)) else {
            return Err(CommandError::failed(format!(
                "{} line {}: expected the columns {}",
                list.display(),
                i + 1,
                header.join(",")
            )));
        };
        let angle: f64 = angle
            .parse()
            .ok()
            .filter(|a: &f64| a.is_finite())
            .ok_or_else(|| {
                CommandError::failed(format!(
                    "{} line {}: {} = {angle:?} is not a finite number",
                    list.display(),
                    i + 1,
                    header[angle_col]
                ))
            })?;
        stack.push((angle, dir.join(file)));
    }
    Ok(stack)
}

/// `analyze aptd`: runs the loop over the stack. The sets are restricted to the stack's angles (the
/// best subset each round); a frame asked for again is served by the next unused copy at that
/// angle, or by the first copy again once all are used (then the "re-acquired" frame repeats,
/// and the JSON counts the reuses).
pub fn aptd_offline(args: &PlanAptdArgs) -> Result<Value, CommandError> {
    use polar_planner::aptd::{detection_scores, empirical_pd, stokes_images};
    use polar_planner::aptd::{Aptd, AptdConfig, AptdFrame, Step, TargetSpec};
    let dir = &args.frames;
    let list = dir.join("frames.csv");
    let text = std::fs::read_to_string(&list)
        .map_err(|e| CommandError::file(format!("{}: cannot read", list.display()), e))?;
    let stack = read_stack_list(&list, &text)?;
    if stack.len() < 3 {
        return Err(CommandError::failed(format!(
            "{}: {} frames; allowed at least 3 at distinct angles",
            list.display(),
            stack.len()
        )));
    }
    let (width, height) = polar_engine::tiff_io::dimensions(&stack[0].1)
        .map_err(|e| CommandError::failed(format!("{}: {e}", stack[0].1.display())))?;
    let mut images = Vec::with_capacity(stack.len());
    for (angle, path) in &stack {
        let px = crate::calibrate::read_tiff(path, width, height).map_err(CommandError::of)?;
        images.push((
            *angle,
            px.iter()
                .map(|&v| f64::from(v) - args.dark_dn)
                .collect::<Vec<f64>>(),
        ));
    }
    let n_px = (width * height) as usize;
    let target = match &args.target_region {
        Some(r) if r.len() == 4 && r[0] < r[2] && r[1] < r[3] && r[2] <= width && r[3] <= height => {
            let mut mask = vec![false; n_px];
            for y in r[1]..r[3] {
                for x in r[0]..r[2] {
                    mask[(y * width + x) as usize] = true;
                }
            }
            TargetSpec::Region(mask)
        }
        Some(r) => {
            return Err(CommandError::input("target_region", format!(
                " = {r:?} is invalid: allowed X0,Y0,X1,Y1 with X0 < X1 <= {width}, Y0 < Y1 <= {height}"
            )))
        }
        None => TargetSpec::Anomalies {
            fraction: args.anomalies,
        },
    };
    let mut available: Vec<f64> = images.iter().map(|(a, _)| a.to_radians()).collect();
    available.sort_by(f64::total_cmp);
    available.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    let initial: Vec<f64> = args
        .initial_angles_deg
        .iter()
        .map(|d| d.to_radians())
        .collect();
    for a in &initial {
        if !available.iter().any(|b| (a - b).abs() < 1e-6) {
            return Err(CommandError::input(
                "initial_angles_deg",
                format!(
                    ": {} is not an angle of the stack (allowed {:?})",
                    a.to_degrees(),
                    available.iter().map(|b| b.to_degrees()).collect::<Vec<_>>()
                ),
            ));
        }
    }
    let (mut aptd, mut step) = Aptd::new(AptdConfig {
        channels: args.channels,
        initial_angles_rad: initial,
        noise_var: args.noise_var,
        // An image stack carries no camera file: the analyzer is taken as ideal.
        instrument: polar_planner::Instrument::ideal(),
        target,
        constraints: Constraints {
            fixed_angles_rad: Some(available),
            ..Constraints::default()
        },
        angle_tol_rad: 0.01f64.to_radians(),
        scr_rel_tol: 0.01,
        frame_budget: args.frame_budget,
    })
    .map_err(planner_error)?;
    let mut used = vec![false; images.len()];
    let mut reused = 0usize;
    let mut last_set = Vec::new();
    while let Step::Acquire(angles) = step {
        last_set = angles.clone();
        let mut frames = Vec::new();
        for a in &angles {
            let same = |i: &usize| (images[*i].0.to_radians() - a).abs() < 1e-6;
            let pick = (0..images.len())
                .find(|i| same(i) && !used[*i])
                .or_else(|| {
                    reused += 1;
                    (0..images.len()).find(|i| same(i))
                })
                .ok_or_else(|| {
                    CommandError::failed(format!("no frame at {} deg", a.to_degrees()))
                })?;
            used[pick] = true;
            frames.push(AptdFrame {
                angle_rad: *a,
                pixels: images[pick].1.clone(),
            });
        }
        step = aptd.on_frames(frames).map_err(planner_error)?;
    }
    // Detection on the Stokes image of every frame used.
    let (s, _) = stokes_images(aptd.frames()).map_err(planner_error)?;
    let mask = aptd.target_mask().to_vec();
    let (rx, mf) = detection_scores(&s, &mask).map_err(planner_error)?;
    let decisions: Vec<Value> = aptd
        .decisions()
        .iter()
        .map(|d| {
            json!({
                "round": d.round,
                "frames_used": d.frames_used,
                "target_pixels": d.target_pixels,
                "scr_last_set": d.scr_last_set,
                "next_angles_deg": d.next_angles_rad.iter().map(|a| a.to_degrees()).collect::<Vec<_>>(),
                "scr_next": d.scr_next,
                "reason": d.reason,
            })
        })
        .collect();
    Ok(json!({
        "angles_deg": last_set.iter().map(|a| a.to_degrees()).collect::<Vec<_>>(),
        "stop": format!("{step:?}"),
        "decisions": decisions,
        "frames_used": aptd.frames().len(),
        "frames_reused": reused,
        "detection": {
            "pfa": args.pfa,
            "pd_rx": empirical_pd(&rx, &mask, args.pfa),
            "pd_matched_filter": empirical_pd(&mf, &mask, args.pfa),
            "target_pixels": mask.iter().filter(|&&t| t).count(),
        },
    }))
}
