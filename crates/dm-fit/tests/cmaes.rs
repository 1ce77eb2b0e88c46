//! CMA-ES on standard test functions; determinism; bounds; gain selection.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use dm_fit::optim::{Bounds, Cmaes, CmaesOptions, CmaesResult, StopReason, minimize};

fn sphere(x: &[f64]) -> f64 {
    x.iter().map(|v| v * v).sum()
}

fn rosenbrock(x: &[f64]) -> f64 {
    x.windows(2)
        .map(|w| 100.0 * (w[1] - w[0] * w[0]).powi(2) + (1.0 - w[0]).powi(2))
        .sum()
}

fn options(seed: u64) -> CmaesOptions {
    CmaesOptions {
        seed,
        ..CmaesOptions::default()
    }
}

fn run_sphere(n: usize, seed: u64) -> CmaesResult {
    let x0 = vec![3.0; n];
    let opts = CmaesOptions {
        target_fitness: Some(1e-10),
        ..options(seed)
    };
    minimize(sphere, &x0, 2.0, None, opts).expect("sphere run")
}

#[test]
fn sphere_2d_and_10d_reach_1e_minus_10() {
    for n in [2, 10] {
        for seed in 0..3 {
            let result = run_sphere(n, seed);
            eprintln!(
                "sphere {n}D seed {seed}: f {:.2e} after {} evaluations ({} generations)",
                result.best_fitness, result.evaluations, result.generations
            );
            assert_eq!(result.stop_reason, StopReason::TargetFitness);
            assert!(result.best_fitness < 1e-10, "f {}", result.best_fitness);
        }
    }
}

#[test]
fn rosenbrock_2d_reaches_the_optimum() {
    for seed in 0..5 {
        let opts = CmaesOptions {
            max_evaluations: Some(20_000),
            ..options(seed)
        };
        let result = minimize(rosenbrock, &[-1.2, 1.0], 0.5, None, opts).expect("run");
        eprintln!(
            "rosenbrock 2D seed {seed}: x {:?} f {:.2e} after {} evaluations, stop {:?}",
            result.best_x, result.best_fitness, result.evaluations, result.stop_reason
        );
        for v in &result.best_x {
            assert!((v - 1.0).abs() < 1e-4, "seed {seed}: {:?}", result.best_x);
        }
    }
}

#[test]
fn same_seed_same_result_and_thread_count_does_not_matter() {
    let run = |threads: usize, seed: u64| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool");
        pool.install(|| minimize(rosenbrock, &[-1.2, 1.0, 0.5, 0.0], 0.5, None, options(seed)))
            .expect("run")
    };
    let one_thread = run(1, 7);
    let two_threads = run(2, 7);
    let again = run(2, 7);
    assert_eq!(one_thread, two_threads);
    assert_eq!(two_threads, again);
    let bits = |r: &CmaesResult| r.best_x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&one_thread), bits(&two_threads));
    let other_seed = run(2, 8);
    assert_ne!(one_thread.best_x, other_seed.best_x);
}

#[test]
fn bounds_are_respected_and_a_boundary_optimum_is_found() {
    // Unconstrained optimum (5, -5, 0.3) lies outside the box in two coordinates.
    let bounds = Bounds::new(vec![-1.0, -1.0, -1.0], vec![1.0, 1.0, 1.0]).expect("bounds");
    let outside = AtomicBool::new(false);
    let check_bounds = bounds.clone();
    let objective = |x: &[f64]| {
        if !check_bounds.contains(x) {
            outside.store(true, Ordering::Relaxed);
        }
        (x[0] - 5.0).powi(2) + (x[1] + 5.0).powi(2) + (x[2] - 0.3).powi(2)
    };
    let opts = CmaesOptions {
        max_evaluations: Some(5000),
        ..options(3)
    };
    let result =
        minimize(objective, &[0.0, 0.0, 0.0], 0.5, Some(bounds.clone()), opts).expect("run");
    eprintln!(
        "bounded: x {:?} after {} evaluations, stop {:?}",
        result.best_x, result.evaluations, result.stop_reason
    );
    assert!(!outside.load(Ordering::Relaxed), "a candidate left the box");
    assert!(bounds.contains(&result.best_x) && bounds.contains(&result.mean));
    assert!((result.best_x[0] - 1.0).abs() < 1e-6);
    assert!((result.best_x[1] + 1.0).abs() < 1e-6);
    assert!((result.best_x[2] - 0.3).abs() < 1e-4);
    assert!(result.evaluations <= 5000);

    // Also through ask/tell with a large σ, where most samples are mirrored.
    let bounds = Bounds::new(vec![0.0, 10.0], vec![1.0, 10.5]).expect("bounds");
    let mut es = Cmaes::new(&[0.5, 10.25], 5.0, Some(bounds.clone()), options(1)).expect("es");
    for _ in 0..20 {
        let population = es.ask();
        assert!(population.iter().all(|x| bounds.contains(x)));
        let fitness: Vec<f64> = population.iter().map(|x| sphere(x)).collect();
        es.tell(&fitness).expect("tell");
    }
}

/// Gain selection searches log-gains: x = (log10 k_p, log10 k_d) over
/// k_p ∈ [1, 1e5], k_d ∈ [0.1, 1e3]. The stand-in for the rollout loss is a
/// smooth, correlated bowl in log space around (k_p, k_d) = (3e3, 20).
#[test]
fn gain_selection_in_log_space() {
    let bounds = Bounds::new(vec![0.0, -1.0], vec![5.0, 3.0]).expect("bounds");
    let evaluations = AtomicU64::new(0);
    let loss = |log_gains: &[f64]| {
        evaluations.fetch_add(1, Ordering::Relaxed);
        let (kp, kd) = (10f64.powf(log_gains[0]), 10f64.powf(log_gains[1]));
        let a = (kp / 3e3).log10();
        let b = (kd / 20.0).log10();
        1.0 + a * a + 0.5 * b * b + 0.4 * a * b
    };
    // Default gains k_p = 100, k_d = 1 as the start; σ0 ≈ a quarter of the box.
    let opts = CmaesOptions {
        max_evaluations: Some(600),
        tol_fun: 1e-10,
        ..options(11)
    };
    let result = minimize(loss, &[2.0, 0.0], 1.2, Some(bounds.clone()), opts).expect("run");
    let (kp, kd) = (10f64.powf(result.best_x[0]), 10f64.powf(result.best_x[1]));
    eprintln!(
        "gains: kp {kp:.3} kd {kd:.4} after {} evaluations, stop {:?}",
        result.evaluations, result.stop_reason
    );
    assert!(bounds.contains(&result.best_x));
    assert!((kp / 3e3 - 1.0).abs() < 1e-3, "kp {kp}");
    assert!((kd / 20.0 - 1.0).abs() < 1e-3, "kd {kd}");
    assert_eq!(evaluations.load(Ordering::Relaxed), result.evaluations);
    assert!(result.evaluations <= 600);
}

#[test]
fn checkpoint_between_ask_and_tell_resumes_identically() {
    let run_to_end = |mut es: Cmaes| {
        loop {
            let fitness: Vec<f64> = es.ask().iter().map(|x| rosenbrock(x)).collect();
            es.tell(&fitness).expect("tell");
            if let Some(reason) = es.should_stop() {
                return es.result(reason).expect("result");
            }
        }
    };
    let start = || Cmaes::new(&[0.0, 0.0, 0.0], 0.3, None, options(5)).expect("es");
    let uninterrupted = run_to_end(start());

    let mut es = start();
    for _ in 0..15 {
        let fitness: Vec<f64> = es.ask().iter().map(|x| rosenbrock(x)).collect();
        es.tell(&fitness).expect("tell");
    }
    let pending = es.ask();
    let checkpoint = serde_json::to_string(&es).expect("serialise");
    let mut restored: Cmaes = serde_json::from_str(&checkpoint).expect("deserialise");
    assert_eq!(restored.ask(), pending);
    let resumed = run_to_end(restored);
    assert_eq!(resumed, uninterrupted);
}
