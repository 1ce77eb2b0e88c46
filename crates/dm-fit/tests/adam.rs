//! Adam + clipping on small problems; bitwise checkpoint/resume.

use dm_fit::optim::{Adam, AdamConfig, ClipConfig, ParamSet, clip_physics_gradients};

/// Two groups, as in the fit: e.g. per-patch raw stiffness and a scalar.
fn initial_params() -> ParamSet {
    ParamSet::new()
        .with_group("youngs_raw", vec![2.0, -1.5, 0.3, 4.0])
        .and_then(|set| set.with_group("damping_raw", vec![-3.0]))
        .expect("unique names")
}

/// f(θ) = Σ a_i (θ_i − c_i)² over the flattened groups; returns f and ∇f.
fn quadratic(params: &ParamSet) -> (f64, ParamSet) {
    let curvature = [1.0, 10.0, 0.5, 3.0, 2.0];
    let centre = [0.5, -0.25, 1.0, -2.0, 0.75];
    let mut grads = params.zeros_like();
    let mut value = 0.0;
    let mut k = 0;
    for ((_, g), group) in grads.groups_mut().zip(params.groups()) {
        for (gi, &theta) in g.iter_mut().zip(&group.values) {
            let d = theta - centre[k];
            value += curvature[k] * d * d;
            *gi = 2.0 * curvature[k] * d;
            k += 1;
        }
    }
    (value, grads)
}

/// A non-quadratic gradient so the moment estimates carry real history.
fn wiggly_gradient(params: &ParamSet, step: usize) -> ParamSet {
    let mut grads = params.zeros_like();
    for ((_, g), group) in grads.groups_mut().zip(params.groups()) {
        for (i, (gi, &theta)) in g.iter_mut().zip(&group.values).enumerate() {
            *gi = (theta * 1.7 + i as f64).sin() * 3.0 + 0.01 * step as f64 - theta.powi(3) * 0.2;
        }
    }
    grads
}

#[test]
fn converges_on_a_quadratic_with_clipping() {
    let mut adam = Adam::new(AdamConfig::with_learning_rate(0.05)).expect("config");
    let mut params = initial_params();
    let (start, _) = quadratic(&params);
    for step in 0..3000 {
        // Constant-rate Adam hovers at a noise floor set by the step size; an
        // exponential decay (as a training schedule would) lets it settle.
        adam.set_learning_rate(0.05 * 0.998_f64.powi(step))
            .expect("valid rate");
        let (_, mut grads) = quadratic(&params);
        clip_physics_gradients(&mut grads, &ClipConfig::default()).expect("finite");
        adam.step(&mut params, &grads).expect("step");
    }
    let (end, _) = quadratic(&params);
    eprintln!("quadratic: f {start:.3e} -> {end:.3e} after 3000 steps");
    assert!(end < 1e-12, "f = {end}");
    assert_eq!(adam.step_count(), 3000);
}

#[test]
fn first_step_from_fresh_state_is_learning_rate_times_sign() {
    let lr = 0.01;
    let mut adam = Adam::new(AdamConfig::with_learning_rate(lr)).expect("config");
    let mut params = ParamSet::new()
        .with_group("a", vec![1.0, 1.0, 1.0, 1.0])
        .expect("params");
    let grad_values = [3.0, -0.5, 1e-3, 0.0];
    let grads = ParamSet::new()
        .with_group("a", grad_values.to_vec())
        .expect("grads");
    adam.step(&mut params, &grads).expect("step");
    for (theta, g) in params.get("a").expect("a").iter().zip(grad_values) {
        let step = theta - 1.0;
        // Bias-corrected m̂ = g, v̂ = g², so Δ = −lr g / (|g| + ε).
        let expected = -lr * g.signum() * g.abs() / (g.abs() + 1e-8);
        assert!((step - expected).abs() <= 1e-15, "g {g}: step {step}");
        if g != 0.0 {
            assert!(
                (step + lr * g.signum()).abs() <= lr * 1e-5,
                "g {g}: step {step}"
            );
        } else {
            assert_eq!(step, 0.0);
        }
    }
}

#[test]
fn per_group_learning_rates_apply() {
    let mut config = AdamConfig::with_learning_rate(0.1);
    config
        .group_learning_rates
        .insert("damping_raw".into(), 0.001);
    let mut adam = Adam::new(config).expect("config");
    let mut params = initial_params();
    let before = params.clone();
    let (_, grads) = quadratic(&params);
    adam.step(&mut params, &grads).expect("step");
    let moved = |name: &str| {
        (params.get(name).expect("group")[0] - before.get(name).expect("group")[0]).abs()
    };
    assert!((moved("youngs_raw") - 0.1).abs() < 1e-6);
    assert!((moved("damping_raw") - 0.001).abs() < 1e-8);
}

#[test]
fn checkpoint_restore_continue_is_bitwise_identical() {
    let total = 60;
    let split = 23;
    let config = AdamConfig::with_learning_rate(0.03);

    let mut adam = Adam::new(config.clone()).expect("config");
    let mut params = initial_params();
    let mut uninterrupted = Vec::new();
    for step in 0..total {
        let mut grads = wiggly_gradient(&params, step);
        clip_physics_gradients(&mut grads, &ClipConfig::default()).expect("finite");
        adam.step(&mut params, &grads).expect("step");
        uninterrupted.push(params.flatten());
    }

    let mut adam = Adam::new(config).expect("config");
    let mut params = initial_params();
    for step in 0..split {
        let mut grads = wiggly_gradient(&params, step);
        clip_physics_gradients(&mut grads, &ClipConfig::default()).expect("finite");
        adam.step(&mut params, &grads).expect("step");
    }
    let checkpoint = serde_json::to_string(&(&adam, &params)).expect("serialise");
    drop((adam, params));
    let (mut adam, mut params): (Adam, ParamSet) =
        serde_json::from_str(&checkpoint).expect("deserialise");
    assert_eq!(adam.step_count(), split as u64);
    for step in split..total {
        let mut grads = wiggly_gradient(&params, step);
        clip_physics_gradients(&mut grads, &ClipConfig::default()).expect("finite");
        adam.step(&mut params, &grads).expect("step");
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(
            bits(&params.flatten()),
            bits(&uninterrupted[step]),
            "step {step}"
        );
    }
}

#[test]
fn continued_for_one_group_steps_it_exactly_as_the_whole_optimiser_would() {
    let mut whole = Adam::new(AdamConfig::with_learning_rate(0.05)).expect("config");
    let mut params = initial_params();
    for step in 0..4 {
        let grads = wiggly_gradient(&params, step);
        whole.step(&mut params, &grads).expect("step");
    }
    let only_youngs = |set: &ParamSet| {
        ParamSet::new()
            .with_group("youngs_raw", set.get("youngs_raw").expect("group").to_vec())
            .expect("one group")
    };
    let mut part = whole
        .continued_for_group("youngs_raw", AdamConfig::with_learning_rate(0.05))
        .expect("group held");
    assert_eq!(part.step_count(), 4);
    let mut part_params = only_youngs(&params);
    for step in 4..8 {
        let grads = wiggly_gradient(&params, step);
        whole.step(&mut params, &grads).expect("step");
        part.step(&mut part_params, &only_youngs(&grads))
            .expect("step");
        // Adam is elementwise: the same moments and count give the same bits.
        assert_eq!(part_params, only_youngs(&params), "step {step}");
    }
    assert!(
        whole
            .continued_for_group("no_such_group", AdamConfig::default())
            .is_err()
    );
    // Before any step there is nothing to carry: a fresh optimiser.
    let fresh = Adam::new(AdamConfig::default()).expect("config");
    let continued = fresh
        .continued_for_group("youngs_raw", AdamConfig::default())
        .expect("nothing to carry");
    assert_eq!(continued, fresh);
}
