//! The skylight's slow validation studies, run on demand (`#[ignore]`), compiled into the model
//! crate's unit tests as `skylight::tests::studies` (they use its private items):
//! `cargo test --release -p polar-model --lib studies -- --ignored --nocapture`.

use super::*;

/// One ray: the product rule far past convergence, and its value and cost at each level.
struct Ray {
    truth: [f64; 3],
    levels: Vec<([f64; 3], usize)>,
}

impl Ray {
    fn change(&self, level: usize) -> f64 {
        let (a, b) = (&self.levels[level].0, &self.levels[level - 1].0);
        (0..3).fold(0.0f64, |m, i| m.max((a[i] - b[i]).abs()))
    }

    fn error(&self, level: usize) -> f64 {
        let a = &self.levels[level].0;
        (0..3).fold(0.0f64, |m, i| m.max((a[i] - self.truth[i]).abs()))
    }

    /// The level a ladder from `start` accepts at `tol`, and its cost.
    fn ladder(&self, start: usize, tol: f64) -> (Option<usize>, usize) {
        let mut cost = self.levels[start].1;
        for l in start + 1..self.levels.len() {
            cost += self.levels[l].1;
            if l >= start + 2 && self.change(l).max(self.change(l - 1)) <= tol {
                return (Some(l), cost);
            }
        }
        (None, cost)
    }
}

/// The suns of the pair studies, (zenith, azimuth) in degrees: the rooftop's, low,
/// high, and near the horizon.
const STUDY_SUNS: [(f64, f64); 5] = [
    (33.6, 115.0),
    (70.0, 300.0),
    (10.0, 0.0),
    (25.0, 130.0),
    (85.0, 200.0),
];

/// The level at which a batch hinted at `hint` is accepted on its pairs (`hint - 1`) or
/// its next pairs (`hint`), and the claimed error there (`safety` times the batch's
/// largest change into that level), as `Prepared::points_paired` accepts it.
fn accepted_pair(batch: &[Ray], hint: usize, tol: f64, safety: f64) -> Option<(usize, f64)> {
    [hint - 1, hint]
        .into_iter()
        .take_while(|&upper| upper + 2 <= GAUSS_LEVELS.len())
        .map(|upper| {
            let e = safety * batch.iter().fold(0.0f64, |m, r| m.max(r.change(upper)));
            (upper, e)
        })
        .find(|&(_, e)| e <= tol)
}

/// The validation of [`level_pair`] and [`next_pair`] on vegetation (its hemisphere
/// rule): fields of +-4 and +-6 deg around views 8-68 deg from the normal, 5 suns with
/// an aureole, leaf indices 1.4-1.6, tolerances 1e-2 to 1e-8 of the centre's S0; the
/// centre's ladder hints the other 12 rays (corners, edges and checks). For safety
/// factors 1-3 on the batch's largest change, which hints keep every ray within its
/// claim; the adopted [`pair_rule`] must keep all of them.
#[test]
#[ignore = "a study: about 1 minute"]
fn vegetation_pair_study() {
    let safeties = [1.0, 1.5, 2.0, 3.0];
    // The adopted rule, whose costs are counted and whose short rays are printed.
    let rule =
        pair_rule(&Surface::vegetation(RefractiveIndex::new(1.5, 0.0).unwrap(), 0.01).unwrap());
    let adopted = safeties.iter().position(|&f| f == rule.safety).unwrap();
    let nl = GAUSS_LEVELS.len();
    // [safety][hint]: (batches accepted, rays short, worst ratio)
    let mut stats = vec![vec![(0usize, 0usize, 0.0f64); nl]; safeties.len()];
    let (mut cost_ladders, mut cost_pairs) = (vec![0usize; nl], vec![0usize; nl]);
    let mut truth_gap = 0.0f64;
    for half in [4.0f64, 6.0] {
        let g = half / 3f64.sqrt();
        let batch_at = [
            (-half, -half),
            (-half, half),
            (half, -half),
            (half, half),
            (-half, 0.0),
            (0.0, -half),
            (0.0, half),
            (half, 0.0),
            (-g, -g),
            (-g, g),
            (g, -g),
            (g, g),
        ];
        for (sz, sa) in STUDY_SUNS {
            let sky = aureole(sz, sa);
            for n in [1.4, 1.5, 1.6] {
                let surface =
                    Surface::vegetation(RefractiveIndex::new(n, 0.0).unwrap(), 0.01).unwrap();
                for (tv, av) in [8.0, 25.0, 45.0, 60.0, 68.0]
                    .iter()
                    .flat_map(|&t| [(t, 30.0), (t, 200.0)])
                {
                    let ray = |du: f64, dv: f64| {
                        let view = direction_from_deg(tv + du, av + dv);
                        let f = direction_integrand(&surface, &sky, &view);
                        let (phis, mus) = hemisphere_splits(&sky, &view);
                        let truth = hemisphere_gauss(&f, 128, 64, &phis, &mus).0;
                        let check = hemisphere_gauss(&f, 96, 48, &phis, &mus).0;
                        let gap = (0..3).fold(0.0f64, |m, i| m.max((truth[i] - check[i]).abs()));
                        (
                            Ray {
                                truth,
                                levels: GAUSS_LEVELS
                                    .iter()
                                    .map(|&(n, q)| hemisphere_gauss(&f, n, q, &phis, &mus))
                                    .collect(),
                            },
                            gap,
                        )
                    };
                    let (centre, gap) = ray(0.0, 0.0);
                    truth_gap = truth_gap.max(gap / centre.truth[0]);
                    let batch: Vec<Ray> = batch_at.iter().map(|&(u, v)| ray(u, v).0).collect();
                    for rel in [1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8] {
                        let tol = rel * centre.truth[0];
                        let (Some(hint), _) = centre.ladder(0, tol) else {
                            continue;
                        };
                        if hint < 2 {
                            continue;
                        }
                        let ladders: usize = batch.iter().map(|r| r.ladder(hint - 2, tol).1).sum();
                        cost_ladders[hint] += ladders;
                        for (si, &safety) in safeties.iter().enumerate() {
                            let Some((upper, e)) = accepted_pair(&batch, hint, tol, safety) else {
                                if si == adopted {
                                    cost_pairs[hint] += ladders;
                                }
                                continue;
                            };
                            if si == adopted {
                                cost_pairs[hint] += batch
                                    .iter()
                                    .map(|r| {
                                        (hint - 2..=upper).map(|l| r.levels[l].1).sum::<usize>()
                                    })
                                    .sum::<usize>();
                            }
                            let worst = batch.iter().fold(0.0f64, |m, r| m.max(r.error(upper) / e));
                            let st = &mut stats[si][hint];
                            st.0 += 1;
                            st.2 = st.2.max(worst);
                            if worst > 1.0 {
                                st.1 += 1;
                                if si == adopted {
                                    println!("short (adopted rule): half {half} sun {sz}/{sa} n {n} view {tv}/{av} rel {rel} hint {hint} upper {upper}: {worst:.2}x");
                                }
                            }
                        }
                    }
                }
            }
        }
    }
    for (safety, by_hint) in safeties.iter().zip(&stats) {
        for (h, &(b, f, w)) in by_hint.iter().enumerate() {
            if b > 0 {
                println!("safety {safety} hint {h}: {b} batches, {f} short, worst {w:.3}");
            }
        }
    }
    for (h, (pairs, ladders)) in cost_pairs.iter().zip(&cost_ladders).enumerate() {
        if *ladders > 0 {
            println!("hint {h}: pairs (adopted rule) {pairs} against ladders {ladders}");
        }
    }
    println!("truth: (128, 64) against (96, 48) differ by at most {truth_gap:.1e} of S0");
    // The adopted rule: no ray of an admitted batch beyond its claim.
    for (h, &(_, short, worst)) in stats[adopted].iter().enumerate() {
        if (rule.min_hint..=rule.max_hint).contains(&h) {
            assert_eq!(short, 0, "hint {h}: worst {worst:.3}");
        }
    }
    assert!(truth_gap < 1e-9);
}

/// The validation of [`certified_level`]: the sky interpolant's first batch is the
/// cross's four edge rays, hinted by the centre's ladder and accepted on its pairs (or
/// next pairs) as `Prepared::points_paired` accepts them; every later ray (the four
/// checks, the four corners and the four 5-point nodes) takes the batch's upper level
/// with its error, and must be within it of the truth. Fields of +-4 and +-6 deg
/// around views 8-68 deg from the normal, the 5 suns with an aureole, tolerances 1e-2
/// to 1e-8 of the centre's S0; microfacets as in `field_pair_study` (a dielectric and
/// copper, sigma 0.02-1) and vegetation as in `vegetation_pair_study` (leaf indices
/// 1.4-1.6), each with its [`pair_rule`].
#[test]
#[ignore = "a study: about 4 minutes on 2 cores"]
fn certificate_study() {
    use rayon::prelude::*;
    let glass = RefractiveIndex::new(1.5, 0.0).unwrap();
    let copper = RefractiveIndex::new(1.02, 2.58).unwrap();
    let mut surfaces = Vec::new();
    for index in [glass, copper] {
        for sigma in [0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 1.0] {
            surfaces.push(Surface::microfacet(index, sigma, 0.0).unwrap());
        }
    }
    for n in [1.4, 1.5, 1.6] {
        let leaf = RefractiveIndex::new(n, 0.0).unwrap();
        surfaces.push(Surface::vegetation(leaf, 0.01).unwrap());
    }
    let views: Vec<(f64, f64)> = [8.0, 25.0, 45.0, 60.0, 68.0]
        .iter()
        .flat_map(|&t| [(t, 30.0), (t, 200.0)])
        .collect();
    // (surface, sun, half the field, view), each in degrees.
    type Case = (usize, (f64, f64), f64, (f64, f64));
    let cases: Vec<Case> = (0..surfaces.len())
        .flat_map(|s| {
            let views = &views;
            STUDY_SUNS.iter().flat_map(move |&sun| {
                [4.0f64, 6.0]
                    .into_iter()
                    .flat_map(move |half| views.iter().map(move |&v| (s, sun, half, v)))
            })
        })
        .collect();
    // Per case: (vegetation, batches accepted, later rays, rays beyond the claim,
    // worst ratio).
    let stats: Vec<(bool, usize, usize, usize, f64)> = cases
        .par_iter()
        .map(|&(s, (sz, sa), half, (tv, av))| {
            let surface = &surfaces[s];
            let vegetation = matches!(surface, Surface::Vegetation { .. });
            let rule = pair_rule(surface);
            let sky = aureole(sz, sa);
            let (g, r) = (half / 3f64.sqrt(), half / 2f64.sqrt());
            let ray = |du: f64, dv: f64| {
                let view = direction_from_deg(tv + du, av + dv);
                let truth = match surface {
                    Surface::Microfacet { lobe, .. } => {
                        let f = SlopeIntegrand::new(
                            lobe.index().permittivity(),
                            lobe.sigma(),
                            &sky,
                            &view,
                        );
                        f.gauss(160, 64, &mut Vec::new()).0
                    }
                    Surface::Vegetation { .. } => {
                        let f = direction_integrand(surface, &sky, &view);
                        let (phis, mus) = hemisphere_splits(&sky, &view);
                        hemisphere_gauss(&f, 128, 64, &phis, &mus).0
                    }
                };
                Ray {
                    truth,
                    levels: (0..GAUSS_LEVELS.len())
                        .map(|l| rule_level(surface, &sky, &view, l).unwrap())
                        .collect(),
                }
            };
            let centre = ray(0.0, 0.0);
            let edges: Vec<Ray> = [(-half, 0.0), (0.0, -half), (0.0, half), (half, 0.0)]
                .iter()
                .map(|&(u, v)| ray(u, v))
                .collect();
            let later: Vec<Ray> = [
                (-g, -g),
                (-g, g),
                (g, -g),
                (g, g),
                (-half, -half),
                (-half, half),
                (half, -half),
                (half, half),
                (-r, 0.0),
                (r, 0.0),
                (0.0, -r),
                (0.0, r),
            ]
            .iter()
            .map(|&(u, v)| ray(u, v))
            .collect();
            let (mut batches, mut rays, mut short, mut worst) = (0, 0, 0, 0.0f64);
            for rel in [1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8] {
                let tol = rel * centre.truth[0];
                let Some(hint) = centre.ladder(0, tol).0 else {
                    continue;
                };
                if !(rule.min_hint..=rule.max_hint).contains(&hint) {
                    continue;
                }
                let Some((upper, e)) = accepted_pair(&edges, hint, tol, rule.safety) else {
                    continue;
                };
                batches += 1;
                for r in &later {
                    rays += 1;
                    let ratio = r.error(upper) / e;
                    worst = worst.max(ratio);
                    if r.error(upper) > e + 1e-13 * r.truth[0] {
                        short += 1;
                        println!(
                            "short: surface {s} sun {sz}/{sa} half {half} view {tv}/{av} \
                             rel {rel} hint {hint}: {ratio:.2}x"
                        );
                    }
                }
            }
            (vegetation, batches, rays, short, worst)
        })
        .collect();
    for vegetation in [false, true] {
        let (mut batches, mut rays, mut short, mut worst) = (0, 0, 0, 0.0f64);
        for &(v, b, r, s, w) in &stats {
            if v == vegetation {
                (batches, rays, short) = (batches + b, rays + r, short + s);
                worst = worst.max(w);
            }
        }
        let kind = if vegetation {
            "vegetation"
        } else {
            "microfacets"
        };
        println!(
            "{kind}: {batches} batches of edges accepted, {rays} later rays, {short} \
             beyond the batch's error, the worst at {worst:.3} of it"
        );
        assert_eq!(short, 0, "{kind}");
    }
}

/// The validation of [`level_pair`] and [`next_pair`] on microfacets: fields of +-4 and
/// +-6 deg (in view zenith and azimuth) around views 8-68 deg from the normal; 5 suns with
/// an aureole; a dielectric (n 1.5) and a metal (copper); sigma 0.02-1; tolerances 1e-2 to
/// 1e-8 of the centre's S0. Two ways to hint a batch: the centre's ladder hints the other
/// 12 rays (the 3 x 3 Lobatto rays and the four checks), or the centre and corners hint the
/// edges and checks (their lowest level). A batch with `hint >= PAIR_MIN_HINT` is accepted
/// at its pairs, or its next pairs, when the largest change over it meets the tolerance;
/// every ray of an accepted batch must be within that change of the truth.
#[test]
#[ignore = "a study: about 10 minutes"]
fn field_pair_study() {
    let eps = [
        RefractiveIndex::new(1.5, 0.0).unwrap().permittivity(),
        RefractiveIndex::new(1.02, 2.58).unwrap().permittivity(),
    ];
    let mut failures = 0;
    for half in [4.0f64, 6.0] {
        let g = half / 3f64.sqrt();
        let corners = [(-half, -half), (-half, half), (half, -half), (half, half)];
        let edges = [(-half, 0.0), (0.0, -half), (0.0, half), (half, 0.0)];
        let checks = [(-g, -g), (-g, g), (g, -g), (g, g)];
        let centre_only: Vec<(f64, f64)> = vec![(0.0, 0.0)];
        let with_corners: Vec<(f64, f64)> = std::iter::once((0.0, 0.0)).chain(corners).collect();
        let rest: Vec<(f64, f64)> = corners
            .iter()
            .chain(&edges)
            .chain(&checks)
            .copied()
            .collect();
        let edges_checks: Vec<(f64, f64)> = edges.iter().chain(&checks).copied().collect();
        for (scenario, hinting, batch) in [
            ("the centre hints the rest", &centre_only, &rest),
            (
                "centre and corners hint edges and checks",
                &with_corners,
                &edges_checks,
            ),
        ] {
            let (mut batches, mut first, mut next, mut worst) = (0, 0, 0, 0.0f64);
            let (mut cost_ladders, mut cost_pairs) = (0usize, 0usize);
            for (sz, sa) in STUDY_SUNS {
                let sky = aureole(sz, sa);
                for eps in eps {
                    for sigma in [0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 1.0] {
                        for (tv, av) in [8.0, 25.0, 45.0, 60.0, 68.0]
                            .iter()
                            .flat_map(|&t| [(t, 30.0), (t, 200.0)])
                        {
                            let rays = |at: &[(f64, f64)]| -> Vec<Ray> {
                                at.iter()
                                    .map(|&(du, dv)| {
                                        let view = direction_from_deg(tv + du, av + dv);
                                        let f = SlopeIntegrand::new(eps, sigma, &sky, &view);
                                        let mut pieces = Vec::new();
                                        Ray {
                                            truth: f.gauss(160, 64, &mut pieces).0,
                                            levels: GAUSS_LEVELS
                                                .iter()
                                                .map(|&(n, q)| f.gauss(n, q, &mut pieces))
                                                .collect(),
                                        }
                                    })
                                    .collect()
                            };
                            let (hinting, batch) = (rays(hinting), rays(batch));
                            for rel in [1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8] {
                                let tol = rel * hinting[0].truth[0];
                                let levels: Option<Vec<usize>> =
                                    hinting.iter().map(|r| r.ladder(0, tol).0).collect();
                                let Some(hint) = levels.and_then(|l| l.into_iter().min()) else {
                                    continue;
                                };
                                if hint < PAIR_MIN_HINT {
                                    continue;
                                }
                                batches += 1;
                                cost_ladders += batch
                                    .iter()
                                    .map(|r| r.ladder(hint - 2, tol).1)
                                    .sum::<usize>();
                                let Some((upper, e)) = accepted_pair(&batch, hint, tol, 1.0) else {
                                    // Each ray resumes its ladder: the hinted ladder's cost.
                                    cost_pairs += batch
                                        .iter()
                                        .map(|r| r.ladder(hint - 2, tol).1)
                                        .sum::<usize>();
                                    continue;
                                };
                                if upper == hint - 1 {
                                    first += 1;
                                } else {
                                    next += 1;
                                }
                                for r in &batch {
                                    cost_pairs +=
                                        (hint - 2..=upper).map(|l| r.levels[l].1).sum::<usize>();
                                    worst = worst.max(r.error(upper) / e);
                                    if r.error(upper) > e + 1e-13 * r.truth[0] {
                                        failures += 1;
                                        println!(
                                            "short: half {half} sun {sz}/{sa} sigma {sigma} \
                                             view {tv}/{av} rel {rel} hint {hint}: {:.2}x",
                                            r.error(upper) / e
                                        );
                                    }
                                }
                            }
                        }
                    }
                }
            }
            println!(
                "+-{half} deg, {scenario}: {batches} batches, {first} accepted at their \
                 pairs and {next} at the next, worst error {worst:.3} of the batch's change; \
                 {cost_pairs} evaluations against {cost_ladders} for hinted ladders"
            );
        }
    }
    assert_eq!(failures, 0);
}
