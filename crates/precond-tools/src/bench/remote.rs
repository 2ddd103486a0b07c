//! The planning benchmark with a model the planner cannot see inside: a custom domain (a robot
//! in the unit square) whose `f̂ = s + a` is served over HTTP on loopback by a model server the
//! benchmark starts itself (axum, in this process), as a lab's robot would serve its own. The
//! MDE is the service's default GP fitted on 1000 transitions of a true world that differs from
//! the model on a sticky patch. Prints, per proposal, the wall time, the calls to the model and
//! the points they carried.

use super::planning::fit_mde;
use axum::Json;
use axum::Router;
use axum::extract::State;
use axum::routing::post;
use precond::remote_model::RemoteModel;
use precond_core::domain::Problem;
use precond_core::domain::{
    CustomDomain, CustomParams, Domain, DynamicsModel, LabelledTransition, LinearModel, Space,
    Transition,
};
use precond_core::planning::{Planner, PlanningSettings, Precondition, Strategy};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

#[derive(Deserialize)]
struct Batch {
    states: Vec<Vec<f64>>,
    actions: Vec<Vec<f64>>,
}

#[derive(Serialize)]
struct Answer {
    next_states: Vec<Vec<f64>>,
}

/// Calls and points the model server answered.
#[derive(Debug, Default)]
struct Served {
    calls: AtomicU64,
    points: AtomicU64,
}

impl Served {
    /// The calls and the points served so far.
    fn counts(&self) -> (u64, u64) {
        (
            self.calls.load(Ordering::Relaxed),
            self.points.load(Ordering::Relaxed),
        )
    }
}

async fn predict(State(served): State<Arc<Served>>, Json(b): Json<Batch>) -> Json<Answer> {
    served.calls.fetch_add(1, Ordering::Relaxed);
    served
        .points
        .fetch_add(b.states.len() as u64, Ordering::Relaxed);
    Json(Answer {
        next_states: b
            .states
            .iter()
            .zip(&b.actions)
            .map(|(s, a)| s.iter().zip(a).map(|(x, d)| x + d).collect())
            .collect(),
    })
}

/// The true world: `s' = s + a` except on a sticky patch (`x ∈ [0.35, 0.65]`, `y < 0.6`) where
/// the robot makes a fifth of the commanded move.
fn true_step(s: &[f64], a: &[f64]) -> Vec<f64> {
    let k = if (0.35..=0.65).contains(&s[0]) && s[1] < 0.6 {
        0.2
    } else {
        1.0
    };
    s.iter()
        .zip(a)
        .map(|(x, d)| (x + k * d).clamp(0.0, 1.0))
        .collect()
}

fn plane(model: Arc<dyn DynamicsModel>) -> CustomDomain {
    let space = |names: [&str; 2], lo: f64, hi: f64| Space {
        names: names.map(String::from).to_vec(),
        low: vec![lo; 2],
        high: vec![hi; 2],
        values: None,
    };
    let params = CustomParams::plane(
        space(["x", "y"], 0.0, 1.0),
        space(["dx", "dy"], -0.1, 0.1),
        Some(20),
    );
    CustomDomain::new(params, model).expect("the benchmark's domain is valid")
}

/// Runs the benchmark (see the module docs): `repeats` proposals per β, median reported.
pub async fn run(repeats: usize) -> anyhow::Result<()> {
    let served = Arc::new(Served::default());
    let app = Router::new()
        .route("/predict", post(predict))
        .with_state(served.clone());
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let url = format!("http://{}/predict", listener.local_addr()?);
    tokio::spawn(async move { axum::serve(listener, app).await });
    let served_for_bench = served.clone();
    tokio::task::spawn_blocking(move || bench(&url, &served_for_bench, repeats.max(1))).await?
}

fn bench(url: &str, served: &Served, repeats: usize) -> anyhow::Result<()> {
    let calls = precond::remote_model::ModelCalls::new(
        precond::remote_model::ModelUrlPolicy::new(&[url]).map_err(anyhow::Error::msg)?,
        precond::remote_model::ModelCallLimits::default(),
    );
    let model = Arc::new(RemoteModel::new(url, 10_000, 2, Arc::new(calls)));
    let domain = plane(model);
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let data: Vec<LabelledTransition> = (0..1000)
        .map(|_| {
            let s = domain.sample_state(&mut rng);
            let a = domain.sample_action(&s, &mut rng);
            let s_next = true_step(&s, &a);
            let s_pred: Vec<f64> = s
                .iter()
                .zip(&a)
                .map(|(x, d)| (x + d).clamp(0.0, 1.0))
                .collect();
            LabelledTransition {
                deviation: domain.distance(&s_pred, &s_next),
                observed: Transition::new(s, a, s_next),
                s_pred,
            }
        })
        .collect();
    let t0 = Instant::now();
    let mde = fit_mde(&domain, &data, 7)?;
    println!(
        "remote-model planning benchmark: custom 2-D domain, f̂ served over HTTP on loopback ({url}), \
         MDE fitted on 1000 transitions in {:.0} ms; 20 candidates × 5000 extensions, 8 sampled \
         actions per steering step, median of {repeats}",
        t0.elapsed().as_secs_f64() * 1e3
    );
    let settings = PlanningSettings::default();
    let problem = Problem::new(&domain, vec![0.1, 0.3], vec![0.9, 0.3])?;
    let d_max = 0.05;
    // The same domain with the same model in-process: what the network adds.
    let eye = vec![vec![1.0, 0.0], vec![0.0, 1.0]];
    let (st, ac) = (domain.state_space(), domain.action_space());
    let local = plane(Arc::new(LinearModel::new(
        eye.clone(),
        eye,
        vec![0.0; 2],
        st,
        ac,
    )?));
    let propose = |domain: &CustomDomain, at: Precondition, seed: u64| {
        Planner::new(domain, &mde, &settings).propose(Strategy::Active, &problem, at, seed)
    };
    for beta in [-2.0, 0.0, 2.0] {
        let at = Precondition::new(beta, d_max)?;
        let mut runs: Vec<(Duration, u64, u64, String)> = Vec::new();
        for seed in 0..repeats as u64 {
            let (c0, p0) = served.counts();
            let t = Instant::now();
            let p = propose(&domain, at, seed);
            let elapsed = t.elapsed();
            let (c1, p1) = served.counts();
            let (calls, points) = (c1 - c0, p1 - p0);
            let what = match p {
                Ok(p) => format!(
                    "{} runs, {} candidates, {} extensions, chosen length {}",
                    p.runs,
                    p.candidates.len(),
                    p.extensions,
                    p.trajectory.len()
                ),
                Err(e) => e.to_string(),
            };
            runs.push((elapsed, calls, points, what));
        }
        runs.sort_by_key(|r| r.0);
        let (time, calls, points, what) = &runs[runs.len() / 2];
        let mut local_times: Vec<Duration> = (0..repeats as u64)
            .map(|seed| {
                let t = Instant::now();
                let _ = propose(&local, at, seed);
                t.elapsed()
            })
            .collect();
        local_times.sort();
        println!(
            "  proposal (active, β = {beta:>4}): {:>8.1} ms, {calls} model calls, {points} points  [{what}]; in-process model {:.1} ms",
            time.as_secs_f64() * 1e3,
            local_times[local_times.len() / 2].as_secs_f64() * 1e3
        );
    }
    let (c0, p0) = served.counts();
    let t = Instant::now();
    let planner = Planner::new(&domain, &mde, &settings);
    let out = planner.plan(&problem, Precondition::new(2.0, d_max)?, 0)?;
    println!(
        "  test-time plan (β =    2):     {:>8.1} ms, {} model calls, {} points  [found: {}, {} extensions]",
        t.elapsed().as_secs_f64() * 1e3,
        served.calls.load(Ordering::Relaxed) - c0,
        served.points.load(Ordering::Relaxed) - p0,
        out.trajectory.is_some(),
        out.extensions
    );
    let t = Instant::now();
    let _ = planner.propose(
        Strategy::Random,
        &problem,
        Precondition::new(0.0, d_max)?,
        0,
    );
    println!(
        "  proposal (random, β =    0):   {:>8.1} ms",
        t.elapsed().as_secs_f64() * 1e3
    );
    Ok(())
}
