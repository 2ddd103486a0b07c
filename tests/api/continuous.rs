//! Learning on a continuous world, as a robot with a kinematic model would: what it learns
//! spreads between what it executed, and executing closed loop (planning again from where the
//! robot is) reaches goals that open-loop execution misses.

use super::helpers::{TestApp, count_true, fresh_experiment, pushed_lattice};
use precond::domain::{Kinematic, KinematicParams, Problem};
use precond::planning::Trajectory;
use precond::sim::World;
use precond_tools::experiment::reference::ClosedLoop;
use serde_json::{Value, json};

/// The body that asks for a proposal or a plan for `problem`.
fn ask(problem: &Problem) -> Value {
    json!({"start": problem.start(), "goal": problem.goal()})
}

/// The kinematic unit square with moves of at most 0.1 per axis.
fn square() -> Kinematic {
    Kinematic::new(KinematicParams::default()).unwrap()
}

fn trajectory_of(plan: &Value) -> Trajectory {
    let rows = |k: &str| -> Vec<Vec<f64>> {
        plan[k]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| {
                r.as_array()
                    .unwrap()
                    .iter()
                    .map(|x| x.as_f64().unwrap())
                    .collect()
            })
            .collect()
    };
    let nums = |k: &str| -> Vec<f64> {
        plan[k]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect()
    };
    Trajectory {
        states: rows("states"),
        actions: rows("actions"),
        mu: nums("mu"),
        sigma: nums("sigma"),
    }
}

/// Learning on the pusher world (a puck that slides on after each push, far on a wet patch):
/// the paper's loop for a few iterations, the robot's model kinematic.
#[tokio::test]
async fn after_a_few_iterations_unseen_moves_between_seen_ones_are_trusted_and_plans_found() {
    use precond::domain::{Domain, LocalModel};
    use precond::sim::ContinuousWorld;
    use rand::SeedableRng;
    let world = ContinuousWorld::pusher();
    let domain = world.domain();
    let d_max = world.d_max();
    let p = world.params();
    let (_dir, app, id) = fresh_experiment(json!({
        "domain": {"kind": "kinematic", "state_low": p.state_low, "state_high": p.state_high,
                   "action_low": p.action_low, "action_high": p.action_high,
                   "goal_radius": p.goal_radius},
        "d_max": d_max,
        "seed": 1,
        "mde": {"restarts": 1},
        "learning": {"batch_size": 5, "iterations": 6, "n_candidates": 8,
                     "max_extensions": 2000}
    }))
    .await;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
    let mut executed: Vec<(Vec<f64>, Vec<f64>)> = Vec::new();
    let mut posted = 0;
    for _ in 0..6 {
        for _ in 0..5 {
            let problem = world.sample_problem(&domain, &mut rng);
            let (status, proposal) = app.propose(id, &ask(&problem)).await;
            if status != 201 {
                continue;
            }
            let plan = trajectory_of(&proposal["trajectory"]);
            let mut s = plan.states[0].clone();
            let mut transitions = Vec::new();
            for a in &plan.actions {
                let next = world.step(&s, a);
                transitions.push(json!({"s": s, "a": a, "s_next": next}));
                executed.push((s.clone(), a.clone()));
                s = next;
            }
            app.store_trajectory(
                id,
                &json!({"proposal_id": proposal["id"], "transitions": transitions}),
            )
            .await;
            posted += 1;
        }
        app.wait_for_model(id, posted - posted % 5).await;
    }
    assert!(posted >= 25, "{posted} trajectories executed");
    // Unseen moves between seen ones: midway between two executed state-actions 0.1 to 0.3
    // apart, at least 0.03 from every executed state, and truly within d_max.
    let mut probes = Vec::new();
    let mut tries = 0;
    while probes.len() < 40 && tries < 20_000 {
        tries += 1;
        let i = rand::Rng::random_range(&mut rng, 0..executed.len());
        let j = rand::Rng::random_range(&mut rng, 0..executed.len());
        let (si, ai) = &executed[i];
        let (sj, aj) = &executed[j];
        let gap = domain.distance(si, sj);
        if !(0.1..=0.3).contains(&gap) {
            continue;
        }
        let s: Vec<f64> = si.iter().zip(sj).map(|(x, y)| 0.5 * (x + y)).collect();
        let a: Vec<f64> = ai.iter().zip(aj).map(|(x, y)| 0.5 * (x + y)).collect();
        let unseen = executed.iter().all(|(e, _)| domain.distance(e, &s) > 0.03);
        let safe = domain.distance(&domain.predict(&s, &a), &world.step(&s, &a)) < d_max;
        if unseen && safe && world.possible(&s) {
            probes.push(json!({"s": s, "a": a}));
        }
    }
    assert!(probes.len() >= 20, "{} probes", probes.len());
    let (status, judged) = app
        .post_at(id, "precondition", &json!({ "points": probes }))
        .await;
    assert_eq!(status, 200, "{judged}");
    let trusted = count_true(&judged["results"], "inside");
    assert!(
        2 * trusted >= probes.len(),
        "{trusted} of {} safe unseen moves between executed ones trusted at β = 2",
        probes.len()
    );
    // Test plans are found, and their steps are truly within d_max but for a few: of all
    // planned steps, at most one in ten beyond it (the harness's `unsafe_step_rate`). A single
    // plan may still cross the post, a contact few executions have shown: over experiment seeds
    // 1–16 of this test, some plan had more than a tenth of its steps beyond d_max in 7 of 15
    // seeds (9 of 15 with `state_action` features), while all planned steps together stayed
    // within the bound in 13 of 15 (12 of 15) — issue 22's notes.
    let (mut found, mut planned, mut wrong) = (0, 0, 0);
    for _ in 0..10 {
        let problem = world.sample_problem(&domain, &mut rng);
        let (status, plan) = app.post_at(id, "plans", &ask(&problem)).await;
        assert_eq!(status, 200, "{plan}");
        if plan["found"] == true {
            found += 1;
            let t = trajectory_of(&plan["trajectory"]);
            planned += t.actions.len();
            wrong += t
                .states
                .iter()
                .zip(&t.actions)
                .filter(|(s, a)| domain.distance(&domain.predict(s, a), &world.step(s, a)) >= d_max)
                .count();
        }
    }
    assert!(
        wrong * 10 <= planned,
        "{wrong} of {planned} planned steps beyond d_max"
    );
    assert!(found >= 5, "test plans found for {found} of 10 problems");
    app.stop().await;
}

/// Every step drifts 0.012 towards +y: each within d_max = 0.02, but they add up.
#[derive(Debug)]
struct Drift;

impl World for Drift {
    fn reset(&mut self, _rng: &mut dyn rand::RngCore) {}
    fn step(&mut self, s: &[f64], a: &[f64]) -> Vec<f64> {
        vec![
            (s[0] + a[0]).clamp(0.0, 1.0),
            (s[1] + a[1] + 0.012).clamp(0.0, 1.0),
        ]
    }
}

#[tokio::test]
async fn closed_loop_execution_reaches_goals_open_loop_misses() {
    let (_dir, app, id) = fresh_experiment(json!({
        "domain": {"kind": "kinematic", "goal_radius": 0.03},
        "d_max": 0.02,
        "mde": {"restarts": 0},
        "learning": {"batch_size": 1}
    }))
    .await;
    // Show the model that moves are right to within 0.012 everywhere.
    let mut transitions = Vec::new();
    for i in 0..8 {
        for j in 0..8 {
            let s = [0.05 + 0.12 * i as f64, 0.05 + 0.12 * j as f64];
            for a in [
                [0.1, 0.0],
                [-0.1, 0.0],
                [0.0, 0.1],
                [0.0, -0.1],
                [0.07, 0.07],
            ] {
                let n = Drift.step(&s, &a);
                transitions.push(json!({"s": s, "a": a, "s_next": n}));
            }
        }
    }
    app.store_trajectory(id, &json!({ "transitions": transitions }))
        .await;
    app.wait_for_model(id, 1).await;
    let domain = square();
    let (mut open_hits, mut closed_hits) = (0, 0);
    let problems = [
        ([0.1, 0.5], [0.9, 0.5]),
        ([0.1, 0.2], [0.9, 0.3]),
        ([0.9, 0.8], [0.1, 0.7]),
    ];
    for (start, goal) in problems {
        let problem = Problem::new(&domain, start.to_vec(), goal.to_vec()).unwrap();
        let (_, plan) = app
            .post_at(id, "plans", &json!({"start": start, "goal": goal}))
            .await;
        assert_eq!(plan["found"], true, "{plan}");
        let first = trajectory_of(&plan["trajectory"]);
        // Open loop: the plan's actions, whatever happens.
        let mut s = start.to_vec();
        for a in &first.actions {
            s = Drift.step(&s, a);
        }
        open_hits += usize::from(precond::domain::Domain::is_goal(&domain, &s, &goal));
        // Closed loop: plan again from where the robot is when it strays beyond d_max.
        let mut closed = ClosedLoop::new(&problem, first, 0.02);
        while let Some(at) = closed.advance(&mut Drift, &domain, &problem) {
            let (_, again) = app
                .post_at(id, "plans", &json!({"start": at, "goal": goal}))
                .await;
            closed.replanned((again["found"] == true).then(|| trajectory_of(&again["trajectory"])));
        }
        closed_hits += usize::from(closed.executed().success);
        assert!(closed.executed().replans > 0 || closed.executed().success);
    }
    assert_eq!(
        (open_hits, closed_hits),
        (0, problems.len()),
        "open-loop {open_hits}, closed-loop {closed_hits} of {} goals",
        problems.len()
    );
    app.stop().await;
}

/// `learning.calibrate_test_beta`: every version says the β its held-out training transitions
/// certify, test plans and default judgements use it when the setting is on (at most
/// `test_beta`) and `test_beta` when off, and the choice is kept across a restart.
#[tokio::test]
async fn a_calibrated_test_beta_is_the_one_the_version_certifies_and_survives_a_restart() {
    let body = |calibrate: bool| {
        json!({
            "domain": {"kind": "kinematic"},
            "d_max": 0.05,
            "mde": {"kernel": "matern52", "label_cap": 0, "restarts": 0},
            "learning": {"batch_size": 2, "calibrate_test_beta": calibrate}
        })
    };
    let (_dir, app, calibrated) = fresh_experiment(body(true)).await;
    let fixed = app.create_experiment(body(false)).await;
    let (_, e) = app.get_at(calibrated, "").await;
    assert_eq!(e["learning"]["calibrate_test_beta"], true, "{e}");
    for id in [calibrated, fixed] {
        for k in 0..2 {
            app.store_trajectory(id, &pushed_lattice(180, 180 * k))
                .await;
        }
    }
    let point = json!({"points": [{"s": [0.2, 0.5], "a": [0.05, 0.0]}]});
    let mut certified = f64::NAN;
    for (id, calibrate) in [(calibrated, true), (fixed, false)] {
        let model = app.wait_for_model(id, 2).await;
        let choice = &model["beta_choice"];
        let beta = choice["beta"].as_f64().expect("an exact fit certifies a β");
        assert!((0.0..=2.0).contains(&beta), "{model}");
        let unsafe_n = choice["unsafe_transitions"].as_u64().unwrap();
        assert_eq!(
            choice["safe"].as_u64().unwrap() + unsafe_n,
            model["n_train"].as_u64().unwrap()
        );
        assert!(unsafe_n >= 49, "the pushed half is unsafe: {model}");
        if beta < 2.0 {
            let trusted = choice["trusted_unsafe"].as_f64().unwrap();
            assert!((trusted + 1.0) / (unsafe_n as f64 + 2.0) <= 0.02, "{model}");
        }
        let in_use = if calibrate { beta } else { 2.0 };
        assert_eq!(model["test_beta"].as_f64(), Some(in_use), "{model}");
        let (status, judged) = app.post_at(id, "precondition", &point).await;
        assert_eq!(status, 200, "{judged}");
        assert_eq!(judged["beta"].as_f64(), Some(in_use), "{judged}");
        let (_, plan) = app
            .post_at(
                id,
                "plans",
                &json!({"start": [0.1, 0.1], "goal": [0.3, 0.1]}),
            )
            .await;
        assert_eq!(plan["beta"].as_f64(), Some(in_use), "{plan}");
        if calibrate {
            certified = beta;
        }
    }
    let app = app.restart().await;
    let (_, model) = app.get_at(calibrated, "model").await;
    assert_eq!(
        model["beta_choice"]["beta"].as_f64(),
        Some(certified),
        "{model}"
    );
    assert_eq!(model["test_beta"].as_f64(), Some(certified), "{model}");
}

/// `learning.local_test_margin`: default judgements and test plans judge each state-action at
/// its locally calibrated β — never above the test β, so whatever β 2 trusts stays trusted,
/// and below it where the held-out training transitions nearby show it safe; the plan reports
/// the model's own μ and σ; the margin is rebuilt the same after a restart; a request's own β
/// is used as asked.
#[tokio::test]
async fn a_local_margin_trusts_at_least_what_the_test_beta_does_and_survives_a_restart() {
    let body = json!({
        "domain": {"kind": "kinematic"},
        "d_max": 0.05,
        "mde": {"kernel": "matern52", "label_cap": 0, "restarts": 0},
        "learning": {"batch_size": 3, "local_test_margin": true}
    });
    let (_dir, app, id) = fresh_experiment(body).await;
    let (_, e) = app.get_at(id, "").await;
    assert_eq!(e["learning"]["local_test_margin"], true, "{e}");
    // The pushed lattice with scatter: safe moves deviate by up to 0.048 (below d_max, but
    // σ then keeps `μ + 2σ` above it), pushed ones by 0.1 and more.
    for k in 0..3 {
        let mut t = pushed_lattice(150, 150 * k);
        for (j, step) in t["transitions"]
            .as_array_mut()
            .unwrap()
            .iter_mut()
            .enumerate()
        {
            let scatter = 0.048 * ((150 * k + j) as f64 * 0.618_034).fract();
            let y = step["s_next"][1].as_f64().unwrap();
            step["s_next"][1] = json!(y + scatter);
        }
        app.store_trajectory(id, &t).await;
    }
    app.wait_for_model(id, 3).await;
    // A line across the lattice, through the safe half (x < 0.5) into the pushed one.
    let points: Vec<Value> = (0..60)
        .map(|k| json!({"s": [k as f64 / 60.0, 0.3 + (k % 7) as f64 / 40.0], "a": [0.05, 0.0]}))
        .collect();
    let local = judge(&app, id, &points, None).await;
    let at_two = judge(&app, id, &points, Some(2.0)).await;
    assert_eq!(at_two["beta"].as_f64(), Some(2.0));
    let (mut gained, mut unsafe_trusted) = (0, 0);
    for (k, (l, g)) in local["results"]
        .as_array()
        .unwrap()
        .iter()
        .zip(at_two["results"].as_array().unwrap())
        .enumerate()
    {
        let (mu, sigma) = (l["mu"].as_f64().unwrap(), l["sigma"].as_f64().unwrap());
        let upper = l["upper"].as_f64().unwrap();
        assert_eq!(g["mu"].as_f64(), Some(mu));
        assert!(
            upper <= mu + 2.0 * sigma + 1e-12,
            "point {k}: {l} above β 2"
        );
        assert!(upper >= mu - 1e-12, "point {k}: {l} below β 0");
        assert_eq!(l["inside"].as_bool(), Some(upper < 0.05), "point {k}: {l}");
        if g["inside"] == true {
            assert_eq!(
                l["inside"], true,
                "point {k}: trusted at β 2, not locally: {l}"
            );
        } else if l["inside"] == true {
            gained += 1;
        }
        // The truth: a move from x > 0.5 is pushed (deviation 0.1).
        let x = k as f64 / 60.0;
        unsafe_trusted += usize::from(x > 0.5 && l["inside"] == true);
    }
    assert!(
        gained > 0,
        "the local margin trusts nothing β 2 does not: {local}"
    );
    assert_eq!(unsafe_trusted, 0, "{local}");
    // A test plan reports the model's own μ and σ for its steps.
    let (_, plan) = app
        .post_at(
            id,
            "plans",
            &json!({"start": [0.05, 0.3], "goal": [0.4, 0.3]}),
        )
        .await;
    assert_eq!(plan["found"], true, "{plan}");
    let t = trajectory_of(&plan["trajectory"]);
    let steps: Vec<Value> = t
        .states
        .iter()
        .zip(&t.actions)
        .map(|(s, a)| json!({"s": s, "a": a}))
        .collect();
    let (_, own) = app
        .post_at(id, "precondition", &json!({"points": steps, "beta": 2.0}))
        .await;
    for (k, j) in own["results"].as_array().unwrap().iter().enumerate() {
        assert!((j["mu"].as_f64().unwrap() - t.mu[k]).abs() < 1e-9, "{plan}");
        assert!(
            (j["sigma"].as_f64().unwrap() - t.sigma[k]).abs() < 1e-9,
            "{plan}"
        );
    }
    // Rebuilt on restore: the same judgements.
    let app = app.restart().await;
    let again = judge(&app, id, &points, None).await;
    assert_eq!(again["results"], local["results"]);
}

/// `POST …/precondition` on `points`, at `beta` or the experiment's default.
async fn judge(app: &TestApp, id: i64, points: &[Value], beta: Option<f64>) -> Value {
    let mut body = json!({ "points": points });
    if let Some(b) = beta {
        body["beta"] = json!(b);
    }
    let (status, j) = app.post_at(id, "precondition", &body).await;
    assert_eq!(status, 200, "{j}");
    j
}
