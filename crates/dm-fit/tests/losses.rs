//! Fitting losses: hand-written gradients against central finite
//! differences, zeros at the optimum, visibility, frame-0 matching,
//! determinism and input errors.

use dm_fit::loss::{
    LengthPreservation, LossError, LossTerms, LossValue, LossWeights, ObservedFrame, PairSelection,
    TrackMatch, chamfer_error, frame_loss, shape_loss,
};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Central-difference step, metres. Points live in a 0.3 m box (object
/// scale), so 1e-6 is far below any nearest-neighbour gap of random points
/// in general position (no assignment switches inside ±h) and large enough
/// that rounding (~ε·|L|/h ≈ 1e-16·1e-2/1e-6 = 1e-12) stays small.
const FD_STEP: f64 = 1e-6;
/// Track and shape are piecewise quadratic: central differences are exact
/// up to rounding (~1e-12 here; gradients are ~1e-3), so a tight bound.
const TOL_QUADRATIC: f64 = 1e-10;
/// Length loss is smooth but not quadratic: truncation error
/// h²/6·|f'''| with |f'''| ≲ 1/(P·L0²) ~ 1e1 gives ~1e-11, plus rounding.
const TOL_SMOOTH: f64 = 1e-9;

fn random_points(rng: &mut ChaCha8Rng, n: usize) -> Vec<[f64; 3]> {
    (0..n)
        .map(|_| {
            [
                rng.random_range(0.0..0.3),
                rng.random_range(0.0..0.3),
                rng.random_range(0.0..0.3),
            ]
        })
        .collect()
}

fn perturbed(rng: &mut ChaCha8Rng, points: &[[f64; 3]], sigma: f64) -> Vec<[f64; 3]> {
    points
        .iter()
        .map(|p| p.map(|c| c + rng.random_range(-sigma..sigma)))
        .collect()
}

/// Max |analytic − central FD| over every coordinate of every particle.
fn max_fd_error(
    predicted: &[[f64; 3]],
    analytic: &LossValue,
    f: impl Fn(&[[f64; 3]]) -> f64,
) -> f64 {
    assert_eq!(analytic.grad.len(), predicted.len());
    let mut worst: f64 = 0.0;
    let mut x = predicted.to_vec();
    for i in 0..x.len() {
        for a in 0..3 {
            let keep = x[i][a];
            x[i][a] = keep + FD_STEP;
            let plus = f(&x);
            x[i][a] = keep - FD_STEP;
            let minus = f(&x);
            x[i][a] = keep;
            let fd = (plus - minus) / (2.0 * FD_STEP);
            worst = worst.max((fd - analytic.grad[i][a]).abs());
        }
    }
    worst
}

fn max_abs_grad(v: &LossValue) -> f64 {
    v.grad
        .iter()
        .flatten()
        .fold(0.0, |m: f64, g| m.max(g.abs()))
}

fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

fn brute_nearest(points: &[[f64; 3]], q: &[f64; 3]) -> usize {
    let mut best = (0, f64::INFINITY);
    for (i, p) in points.iter().enumerate() {
        let d = dist(p, q);
        if d < best.1 {
            best = (i, d);
        }
    }
    best.0
}

/// A scene: frame-0 particles, a later predicted frame, tracked points
/// near particles at frame 0 and observed positions at the later frame.
struct Scene {
    rest: Vec<[f64; 3]>,
    predicted: Vec<[f64; 3]>,
    observed0: Vec<[f64; 3]>,
    observed: Vec<[f64; 3]>,
    visible: Vec<bool>,
    surface_count: usize,
}

fn scene(seed: u64) -> Scene {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let rest = random_points(&mut rng, 60);
    let predicted = perturbed(&mut rng, &rest, 0.02);
    let observed0: Vec<[f64; 3]> = perturbed(&mut rng, &rest[..25], 0.01);
    let observed = perturbed(&mut rng, &observed0, 0.03);
    let visible = (0..observed.len()).map(|k| k % 4 != 1).collect();
    Scene {
        rest,
        predicted,
        observed0,
        observed,
        visible,
        surface_count: 40,
    }
}

#[test]
fn track_gradient_matches_finite_differences() {
    let s = scene(1);
    let m = TrackMatch::new(&s.rest, &s.observed0).expect("match");
    let loss = m
        .track_loss(&s.predicted, &s.observed, &s.visible)
        .expect("loss");
    let err = max_fd_error(&s.predicted, &loss, |x| {
        m.track_loss(x, &s.observed, &s.visible)
            .expect("loss")
            .value
    });
    eprintln!(
        "track: L = {:.3e}, max|grad| = {:.3e}, max FD error = {err:.3e}",
        loss.value,
        max_abs_grad(&loss)
    );
    assert!(loss.value > 0.0);
    assert!(err < TOL_QUADRATIC, "FD error {err}");
}

#[test]
fn shape_gradient_matches_finite_differences() {
    let s = scene(2);
    let loss = shape_loss(&s.predicted, s.surface_count, &s.observed, &s.visible).expect("loss");
    let err = max_fd_error(&s.predicted, &loss, |x| {
        shape_loss(x, s.surface_count, &s.observed, &s.visible)
            .expect("loss")
            .value
    });
    eprintln!(
        "shape: L = {:.3e}, max|grad| = {:.3e}, max FD error = {err:.3e}",
        loss.value,
        max_abs_grad(&loss)
    );
    assert!(loss.value > 0.0);
    assert!(err < TOL_QUADRATIC, "FD error {err}");
    // Interior particles are not part of the surface.
    assert!(loss.grad[s.surface_count..].iter().all(|g| *g == [0.0; 3]));
    // Value equals the brute-force definition.
    let surface = &s.predicted[..s.surface_count];
    let (sum, n) = s.observed.iter().zip(&s.visible).filter(|&(_, &v)| v).fold(
        (0.0, 0),
        |(sum, n), (o, _)| {
            (
                sum + dist(&surface[brute_nearest(surface, o)], o).powi(2),
                n + 1,
            )
        },
    );
    assert!((loss.value - sum / n as f64).abs() < 1e-15);
}

#[test]
fn length_gradient_matches_finite_differences() {
    let s = scene(3);
    for selection in [PairSelection::default(), PairSelection::Radius(0.08)] {
        let len = LengthPreservation::new(&s.rest, selection).expect("pairs");
        assert!(!len.pairs().is_empty());
        let loss = len.loss(&s.predicted).expect("loss");
        let err = max_fd_error(&s.predicted, &loss, |x| len.loss(x).expect("loss").value);
        eprintln!(
            "length {selection:?}: {} pairs, L = {:.3e}, max|grad| = {:.3e}, max FD error = {err:.3e}",
            len.pairs().len(),
            loss.value,
            max_abs_grad(&loss)
        );
        assert!(loss.value > 0.0);
        assert!(err < TOL_SMOOTH, "FD error {err}");
    }
}

#[test]
fn frame_loss_is_the_weighted_sum_and_matches_finite_differences() {
    let s = scene(4);
    let track = TrackMatch::new(&s.rest, &s.observed0).expect("match");
    let length = LengthPreservation::new(&s.rest, PairSelection::default()).expect("pairs");
    let terms = LossTerms {
        track: &track,
        length: &length,
        surface_count: s.surface_count,
    };
    let weights = LossWeights {
        track: 0.7,
        shape: 1.3,
        length: 0.4,
    };
    let mut observed = ObservedFrame::new(s.observed.clone(), s.visible.clone()).expect("frame");
    // Track validity stricter than visibility for one point.
    observed.track_valid[0] = false;
    let total = frame_loss(&weights, &terms, &s.predicted, &observed).expect("loss");

    let t = track
        .track_loss(&s.predicted, &observed.points, &observed.track_valid)
        .expect("track");
    let sh = shape_loss(
        &s.predicted,
        s.surface_count,
        &observed.points,
        &observed.visible,
    )
    .expect("shape");
    let l = length.loss(&s.predicted).expect("length");
    assert_eq!(
        (total.track, total.shape, total.length),
        (t.value, sh.value, l.value)
    );
    let expected = 0.7 * t.value + 1.3 * sh.value + 0.4 * l.value;
    assert!((total.total.value - expected).abs() <= 1e-15 * expected);

    let err = max_fd_error(&s.predicted, &total.total, |x| {
        frame_loss(&weights, &terms, x, &observed)
            .expect("loss")
            .total
            .value
    });
    eprintln!(
        "frame_loss: L = {:.3e}, max FD error = {err:.3e}",
        total.total.value
    );
    assert!(err < TOL_SMOOTH, "FD error {err}");

    let defaults = LossWeights::default();
    assert_eq!(
        (defaults.track, defaults.shape, defaults.length),
        (1.0, 1.0, 0.1)
    );
}

#[test]
fn zero_at_the_optimum() {
    let s = scene(5);
    // Tracked points sitting exactly on particles, observed there too.
    let picks = [3usize, 17, 29, 0, 44, 51, 8];
    let on_particles: Vec<[f64; 3]> = picks.iter().map(|&i| s.rest[i]).collect();
    let visible = vec![true; picks.len()];
    let m = TrackMatch::new(&s.rest, &on_particles).expect("match");
    assert_eq!(m.particles(), picks);
    let t = m
        .track_loss(&s.rest, &on_particles, &visible)
        .expect("loss");
    assert_eq!(t.value, 0.0);
    assert!(t.grad.iter().all(|g| *g == [0.0; 3]));
    assert_eq!(
        m.track_error(&s.rest, &on_particles, &visible),
        Ok(Some(0.0))
    );

    // Observed points on surface particles (interior ones would not count).
    let on_surface: Vec<[f64; 3]> = s.rest[..s.surface_count]
        .iter()
        .step_by(3)
        .copied()
        .collect();
    let vis = vec![true; on_surface.len()];
    let sh = shape_loss(&s.rest, s.surface_count, &on_surface, &vis).expect("loss");
    assert_eq!(sh.value, 0.0);
    assert!(sh.grad.iter().all(|g| *g == [0.0; 3]));
    assert_eq!(
        chamfer_error(&s.rest, s.surface_count, &on_surface, &vis),
        Ok(Some(0.0))
    );

    // Length: zero at rest, and (to rounding) under a rigid motion.
    let len = LengthPreservation::new(&s.rest, PairSelection::default()).expect("pairs");
    let l = len.loss(&s.rest).expect("loss");
    assert_eq!(l.value, 0.0);
    assert!(l.grad.iter().all(|g| *g == [0.0; 3]));
    let (c, sn) = (0.6_f64.cos(), 0.6_f64.sin());
    let moved: Vec<[f64; 3]> = s
        .rest
        .iter()
        .map(|p| {
            [
                c * p[0] - sn * p[1] + 0.5,
                sn * p[0] + c * p[1] - 0.2,
                p[2] + 1.0,
            ]
        })
        .collect();
    let l = len.loss(&moved).expect("loss");
    eprintln!("length under a rigid motion: {:.3e}", l.value);
    assert!(l.value < 1e-28, "{}", l.value);
    // ... but stretching costs.
    let stretched: Vec<[f64; 3]> = s.rest.iter().map(|p| [1.1 * p[0], p[1], p[2]]).collect();
    assert!(len.loss(&stretched).expect("loss").value > 1e-6);
}

#[test]
fn invisible_points_are_ignored() {
    let s = scene(6);
    let m = TrackMatch::new(&s.rest, &s.observed0).expect("match");
    let base_t = m
        .track_loss(&s.predicted, &s.observed, &s.visible)
        .expect("loss");
    let base_s = shape_loss(&s.predicted, s.surface_count, &s.observed, &s.visible).expect("loss");
    // Invisible points moved far away, or NaN: nothing changes.
    for garbage in [[5.0, -7.0, 9.0], [f64::NAN; 3]] {
        let mut observed = s.observed.clone();
        for (o, &v) in observed.iter_mut().zip(&s.visible) {
            if !v {
                *o = garbage;
            }
        }
        let t = m
            .track_loss(&s.predicted, &observed, &s.visible)
            .expect("loss");
        let sh = shape_loss(&s.predicted, s.surface_count, &observed, &s.visible).expect("loss");
        assert_eq!(t, base_t);
        assert_eq!(sh, base_s);
    }
    // The mean is over visible points only: one visible point alone.
    let mut only = vec![false; s.visible.len()];
    only[2] = true;
    let t = m
        .track_loss(&s.predicted, &s.observed, &only)
        .expect("loss");
    let p = m.particles()[2];
    assert_eq!(t.value, dist(&s.predicted[p], &s.observed[2]).powi(2));
    // None visible: zero value and gradient; errors undefined.
    let none = vec![false; s.visible.len()];
    let t = m
        .track_loss(&s.predicted, &s.observed, &none)
        .expect("loss");
    let sh = shape_loss(&s.predicted, s.surface_count, &s.observed, &none).expect("loss");
    for v in [t, sh] {
        assert_eq!(v.value, 0.0);
        assert_eq!(v.grad.len(), s.predicted.len());
        assert!(v.grad.iter().all(|g| *g == [0.0; 3]));
    }
    assert_eq!(m.track_error(&s.predicted, &s.observed, &none), Ok(None));
    assert_eq!(
        chamfer_error(&s.predicted, s.surface_count, &s.observed, &none),
        Ok(None)
    );
}

#[test]
fn matching_is_nearest_at_frame_zero_and_stays_fixed() {
    let s = scene(7);
    let m = TrackMatch::new(&s.rest, &s.observed0).expect("match");
    let expected: Vec<usize> = s
        .observed0
        .iter()
        .map(|o| brute_nearest(&s.rest, o))
        .collect();
    assert_eq!(m.particles(), expected);
    assert_eq!(m.point_count(), s.observed0.len());
    assert_eq!(m.particle_count(), s.rest.len());

    // A later frame where every tracked point's matched particle is far
    // away and other particles are nearer: the matching does not follow.
    let mut predicted = s.rest.clone();
    for &p in m.particles() {
        predicted[p] = [p as f64 + 10.0, 0.0, 0.0];
    }
    let visible = vec![true; s.observed0.len()];
    let t = m
        .track_loss(&predicted, &s.observed0, &visible)
        .expect("loss");
    for (i, g) in t.grad.iter().enumerate() {
        assert_eq!(*g != [0.0; 3], m.particles().contains(&i), "particle {i}");
    }
    let err = m
        .track_error(&predicted, &s.observed0, &visible)
        .expect("error")
        .expect("visible");
    let brute: f64 = m
        .particles()
        .iter()
        .zip(&s.observed0)
        .map(|(&p, o)| dist(&predicted[p], o))
        .sum::<f64>()
        / s.observed0.len() as f64;
    assert!((err - brute).abs() < 1e-12 * brute);
    assert!(err > 9.0);
}

#[test]
fn errors_are_plain_mean_distances() {
    let s = scene(8);
    let m = TrackMatch::new(&s.rest, &s.observed0).expect("match");
    let vis: Vec<usize> = (0..s.visible.len()).filter(|&k| s.visible[k]).collect();
    let track = m
        .track_error(&s.predicted, &s.observed, &s.visible)
        .expect("error")
        .expect("visible");
    let brute = vis
        .iter()
        .map(|&k| dist(&s.predicted[m.particles()[k]], &s.observed[k]))
        .sum::<f64>()
        / vis.len() as f64;
    assert!((track - brute).abs() < 1e-14);
    let surface = &s.predicted[..s.surface_count];
    let chamfer = chamfer_error(&s.predicted, s.surface_count, &s.observed, &s.visible)
        .expect("error")
        .expect("visible");
    let brute = vis
        .iter()
        .map(|&k| {
            dist(
                &surface[brute_nearest(surface, &s.observed[k])],
                &s.observed[k],
            )
        })
        .sum::<f64>()
        / vis.len() as f64;
    assert!((chamfer - brute).abs() < 1e-14);
}

#[test]
fn pairs_are_deterministic_and_complete() {
    let s = scene(9);
    let k = 6;
    let a = LengthPreservation::new(&s.rest, PairSelection::Nearest(k)).expect("pairs");
    let b = LengthPreservation::new(&s.rest, PairSelection::Nearest(k)).expect("pairs");
    assert_eq!(a, b);
    let pairs = a.pairs();
    assert!(pairs.windows(2).all(|w| w[0] < w[1]), "sorted, unique");
    assert!(pairs.iter().all(|&(p, q)| p < q));
    // Each particle is paired with its k brute-force nearest others.
    for (p, x) in s.rest.iter().enumerate() {
        let mut others: Vec<(f64, usize)> = s
            .rest
            .iter()
            .enumerate()
            .filter(|&(q, _)| q != p)
            .map(|(q, y)| (dist(x, y), q))
            .collect();
        others.sort_by(|u, v| u.0.total_cmp(&v.0));
        for &(_, q) in &others[..k] {
            assert!(pairs.binary_search(&(p.min(q), p.max(q))).is_ok());
        }
    }
    for (&(p, q), &l0) in pairs.iter().zip(a.rest_lengths()) {
        assert_eq!(l0, dist(&s.rest[p], &s.rest[q]));
    }
    // Radius pairs: exactly the brute-force set.
    let r = 0.07;
    let radius = LengthPreservation::new(&s.rest, PairSelection::Radius(r)).expect("pairs");
    let mut brute = Vec::new();
    for p in 0..s.rest.len() {
        for q in p + 1..s.rest.len() {
            if dist(&s.rest[p], &s.rest[q]) < r {
                brute.push((p, q));
            }
        }
    }
    assert_eq!(radius.pairs(), brute);

    // Losses are bitwise reproducible.
    let m1 = TrackMatch::new(&s.rest, &s.observed0).expect("match");
    let m2 = TrackMatch::new(&s.rest, &s.observed0).expect("match");
    assert_eq!(m1, m2);
    let run = || {
        (
            m1.track_loss(&s.predicted, &s.observed, &s.visible)
                .expect("loss"),
            shape_loss(&s.predicted, s.surface_count, &s.observed, &s.visible).expect("loss"),
            a.loss(&s.predicted).expect("loss"),
        )
    };
    assert_eq!(run(), run());
}

#[test]
fn bad_inputs_are_errors_naming_the_argument() {
    let s = scene(10);
    let m = TrackMatch::new(&s.rest, &s.observed0).expect("match");
    let n = s.observed.len();
    let mismatch = |argument, expected, actual| LossError::LengthMismatch {
        argument,
        expected,
        actual,
    };
    assert_eq!(
        m.track_loss(&s.predicted[1..], &s.observed, &s.visible),
        Err(mismatch("predicted", 60, 59))
    );
    assert_eq!(
        m.track_loss(&s.predicted, &s.observed[1..], &s.visible),
        Err(mismatch("observed", n, n - 1))
    );
    assert_eq!(
        m.track_loss(&s.predicted, &s.observed, &s.visible[1..]),
        Err(mismatch("visible", n, n - 1))
    );
    assert_eq!(
        shape_loss(&s.predicted, s.surface_count, &s.observed, &s.visible[1..]),
        Err(mismatch("visible", n, n - 1))
    );
    assert!(matches!(
        shape_loss(&s.predicted, 61, &s.observed, &s.visible),
        Err(LossError::InvalidArgument {
            argument: "surface_count",
            ..
        })
    ));
    assert!(matches!(
        shape_loss(&s.predicted, 0, &s.observed, &s.visible),
        Err(LossError::Empty { .. })
    ));
    let len = LengthPreservation::new(&s.rest, PairSelection::default()).expect("pairs");
    assert_eq!(
        len.loss(&s.predicted[2..]),
        Err(mismatch("predicted", 60, 58))
    );
    assert!(matches!(
        LengthPreservation::new(&s.rest, PairSelection::Nearest(0)),
        Err(LossError::InvalidArgument {
            argument: "selection",
            ..
        })
    ));
    assert!(matches!(
        LengthPreservation::new(&s.rest, PairSelection::Radius(-1.0)),
        Err(LossError::InvalidArgument {
            argument: "selection",
            ..
        })
    ));
    assert_eq!(
        TrackMatch::new(&[], &s.observed0),
        Err(LossError::Empty {
            argument: "first_frame_particles"
        })
    );

    // A visible NaN observation, or a NaN particle, is an error, not a NaN loss.
    let mut observed = s.observed.clone();
    let k = s.visible.iter().position(|&v| v).expect("a visible point");
    observed[k] = [f64::NAN; 3];
    assert_eq!(
        m.track_loss(&s.predicted, &observed, &s.visible),
        Err(LossError::NonFinite {
            argument: "observed",
            index: k
        })
    );
    assert_eq!(
        shape_loss(&s.predicted, s.surface_count, &observed, &s.visible),
        Err(LossError::NonFinite {
            argument: "observed",
            index: k
        })
    );
    let mut predicted = s.predicted.clone();
    predicted[5][1] = f64::INFINITY;
    assert_eq!(
        len.loss(&predicted),
        Err(LossError::NonFinite {
            argument: "predicted",
            index: 5
        })
    );
    assert_eq!(
        shape_loss(&predicted, s.surface_count, &s.observed, &s.visible),
        Err(LossError::NonFinite {
            argument: "predicted",
            index: 5
        })
    );
    assert!(
        frame_loss(
            &LossWeights {
                track: -1.0,
                ..LossWeights::default()
            },
            &LossTerms {
                track: &m,
                length: &len,
                surface_count: s.surface_count
            },
            &s.predicted,
            &ObservedFrame::new(s.observed.clone(), s.visible.clone()).expect("frame"),
        )
        .is_err()
    );
    assert_eq!(
        ObservedFrame::new(s.observed.clone(), vec![true; 3]),
        Err(mismatch("visible", n, 3))
    );
}
