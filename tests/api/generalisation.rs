//! The learning loop on a small map, driven over HTTP the way a robot drives it: what is
//! learned must reach beyond what was executed (generalisation), learning must go on once β
//! turns positive (exploration), and test-time plans must get better.

use crate::helpers::*;
use precond::domain::{Cell, IcyGridworld, LocalModel, MOVES};
use precond::sim::Simulated;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};
use std::collections::HashSet;

/// An 8×8 map (row y = 0 first) with an ice band and an obstacle block.
const MAP: [&str; 8] = [
    "........", "........", "~~~~~...", "........", "........", "...##...", "........", "........",
];
const ITERATIONS: usize = 8;
const BATCH: usize = 3;

type Pair = (i64, i64, usize);

struct Loop {
    app: TestApp,
    id: i64,
    grid: IcyGridworld,
    rng: ChaCha8Rng,
}

impl Loop {
    fn free_cells(&self) -> Vec<[i64; 2]> {
        let (w, h) = (self.grid.width() as i64, self.grid.height() as i64);
        (0..h)
            .flat_map(|y| (0..w).map(move |x| [x, y]))
            .filter(|&[x, y]| self.grid.cell(x, y) != Some(Cell::Obstacle))
            .collect()
    }

    fn problem(&mut self) -> ([i64; 2], [i64; 2]) {
        let free = self.free_cells();
        loop {
            let s = free[self.rng.random_range(0..free.len())];
            let g = free[self.rng.random_range(0..free.len())];
            if s != g {
                return (s, g);
            }
        }
    }

    /// Executes `actions` from `start` in the true world; the transitions as posted.
    fn execute(&self, start: &[f64], actions: &[Value]) -> Vec<Value> {
        let mut world = self.grid.world();
        let mut s = start.to_vec();
        let mut out = Vec::new();
        for a in actions {
            let a: Vec<f64> = serde_json::from_value(a.clone()).unwrap();
            let next = world.step(&s, &a);
            out.push(json!({"s": s, "a": a, "s_next": next}));
            s = next;
        }
        out
    }

    /// One training trajectory: a proposal for a fresh problem (up to five problems when the
    /// planner finds nothing), executed and posted. The `(cell, move)` pairs it executed, or
    /// `None` when no problem had a plan.
    async fn train(&mut self) -> Option<Vec<Pair>> {
        for _ in 0..5 {
            let (start, goal) = self.problem();
            let (status, p) = self
                .app
                .propose(self.id, &json!({"start": start, "goal": goal}))
                .await;
            if status == 422 {
                continue;
            }
            assert_eq!(status, 201, "{p}");
            let s0 = [start[0] as f64, start[1] as f64];
            let transitions = self.execute(&s0, p["trajectory"]["actions"].as_array().unwrap());
            let executed = transitions
                .iter()
                .map(|t| {
                    let s = &t["s"];
                    let a: Vec<f64> = serde_json::from_value(t["a"].clone()).unwrap();
                    let m = MOVES.iter().position(|m| m[..] == a[..]).unwrap();
                    (
                        s[0].as_f64().unwrap() as i64,
                        s[1].as_f64().unwrap() as i64,
                        m,
                    )
                })
                .collect();
            let (status, body) = self
                .app
                .post_at(
                    self.id,
                    "trajectories",
                    &json!({"proposal_id": p["id"], "transitions": transitions}),
                )
                .await;
            assert_eq!(status, 201, "{body}");
            return Some(executed);
        }
        None
    }

    /// Every `(cell, move)` of the free cells, and whether the precondition (test β) holds.
    async fn inside(&self) -> Vec<(Pair, bool)> {
        let pairs: Vec<Pair> = self
            .free_cells()
            .into_iter()
            .flat_map(|[x, y]| (0..MOVES.len()).map(move |m| (x, y, m)))
            .collect();
        let points: Vec<Value> = pairs
            .iter()
            .map(|&(x, y, m)| json!({"s": [x, y], "a": MOVES[m]}))
            .collect();
        let (status, body) = self
            .app
            .post_at(self.id, "precondition", &json!({ "points": points }))
            .await;
        assert_eq!(status, 200, "{body}");
        let results = body["results"].as_array().unwrap();
        pairs
            .into_iter()
            .zip(results)
            .map(|(p, r)| (p, r["inside"].as_bool().unwrap()))
            .collect()
    }

    /// Whether the true world keeps the move within `d_max` of the model's prediction.
    fn safe(&self, (x, y, m): Pair) -> bool {
        let s = [x as f64, y as f64];
        let truth = self.grid.world().step(&s, &MOVES[m]);
        let predicted = self.grid.predict(&s, &MOVES[m]);
        truth == predicted
    }

    /// Share of `problems` whose test-time plan reaches the goal in the true world.
    async fn success(&self, problems: &[([i64; 2], [i64; 2])]) -> f64 {
        let mut reached = 0;
        for (start, goal) in problems {
            let (status, plan) = self
                .app
                .post_at(self.id, "plans", &json!({"start": start, "goal": goal}))
                .await;
            assert_eq!(status, 200, "{plan}");
            if plan["found"] != true {
                continue;
            }
            let s0 = [start[0] as f64, start[1] as f64];
            let transitions = self.execute(&s0, plan["trajectory"]["actions"].as_array().unwrap());
            let end = transitions
                .last()
                .map_or(json!(s0), |t| t["s_next"].clone());
            if end == json!([goal[0] as f64, goal[1] as f64]) {
                reached += 1;
            }
        }
        reached as f64 / problems.len() as f64
    }

    async fn wait_for_model(&self, n_trajectories: i64) {
        self.app.wait_for_model(self.id, n_trajectories).await;
    }
}

fn inside_set(judged: &[(Pair, bool)]) -> HashSet<Pair> {
    judged.iter().filter(|(_, i)| *i).map(|(p, _)| *p).collect()
}

#[tokio::test]
async fn learning_generalises_beyond_what_was_executed_and_keeps_exploring_once_beta_is_positive() {
    let (_dir, app, id) = fresh_experiment(json!({
        "domain": {"kind": "icy_gridworld", "map": MAP},
        "seed": 5,
        "mde": {"restarts": 1},
        // The paper's acquisition, whose candidates all lie inside the training precondition:
        // what is explored once β > 0 is then the β schedule's doing. (`bottleneck` probes
        // untrusted moves on purpose; it is measured in the harness.)
        "learning": {"iterations": ITERATIONS, "batch_size": BATCH,
                     "n_candidates": 10, "max_extensions": 2000, "acquisition": "lcb"}
    }))
    .await;
    let mut l = Loop {
        app,
        id,
        grid: IcyGridworld::new(&MAP).unwrap(),
        rng: ChaCha8Rng::seed_from_u64(11),
    };
    let test_problems: Vec<_> = (0..12).map(|_| l.problem()).collect();
    // β_j = 4 / (1 + e^{−(j − 4)/2}) − 2 turns positive at j = 5.
    let first_positive = (0..ITERATIONS)
        .find(|&j| 4.0 / (1.0 + (-(j as f64 - 4.0) / 2.0).exp()) - 2.0 > 0.0)
        .unwrap();
    let mut executed: HashSet<Pair> = HashSet::new();
    let mut success_first = None;
    let mut at_first_positive = None;
    let mut executed_before_positive = HashSet::new();
    let mut posted = 0;
    for j in 0..ITERATIONS {
        if j == first_positive {
            at_first_positive = Some(inside_set(&l.inside().await));
            executed_before_positive = executed.clone();
        }
        for _ in 0..BATCH {
            if let Some(pairs) = l.train().await {
                executed.extend(pairs);
                posted += 1;
            }
        }
        // The service refits after every batch of `BATCH` posted trajectories.
        l.wait_for_model((posted / BATCH * BATCH) as i64).await;
        if j == 0 {
            success_first = Some(l.success(&test_problems).await);
        }
    }
    let judged = l.inside().await;
    let inside = inside_set(&judged);

    // Sound: no unsafe move the robot executed is trusted — the model learned from every
    // failure it saw.
    let unsafe_pairs: Vec<Pair> = judged
        .iter()
        .map(|(p, _)| *p)
        .filter(|p| !l.safe(*p))
        .collect();
    let unsafe_inside: Vec<&Pair> = unsafe_pairs.iter().filter(|p| inside.contains(p)).collect();
    let failures_trusted: Vec<_> = unsafe_inside
        .iter()
        .filter(|p| executed.contains(p))
        .collect();
    assert!(
        failures_trusted.is_empty(),
        "executed unsafe moves trusted: {failures_trusted:?}"
    );
    // And far from permissive: at most one unsafe move in eight is trusted. A model that knows
    // nothing of obstacles cannot tell a never-bumped obstacle cell from a free one between two
    // free moves; measured on this map, the default (ν = 1/2) kernel trusts the two up-moves into
    // the 2-cell block at y = 5 (never executed; μ + 2σ = 0.074 and 0.082) of 16 unsafe moves,
    // and no other unsafe move comes within 0.06 of d_max, so the count does not hang on
    // rounding. With ν = 5/2 (`mde.kernel: matern52`) none is trusted — but 177 state-actions
    // are trusted where the default trusts 227, and 0.75 of the test problems solved, not 0.83.
    assert!(
        unsafe_inside.len() * 8 <= unsafe_pairs.len(),
        "{} of {} unsafe state-actions trusted: {unsafe_inside:?}",
        unsafe_inside.len(),
        unsafe_pairs.len()
    );

    // Generalisation: safe moves never executed whose two neighbours along an axis executed
    // the same move are trusted — the precondition is not a lookup table of what was executed.
    let between: Vec<Pair> = judged
        .iter()
        .map(|(p, _)| *p)
        .filter(|&(x, y, m)| {
            !executed.contains(&(x, y, m))
                && l.safe((x, y, m))
                && [(1, 0), (0, 1)].iter().any(|(dx, dy)| {
                    executed.contains(&(x - dx, y - dy, m))
                        && executed.contains(&(x + dx, y + dy, m))
                })
        })
        .collect();
    let trusted_between = between.iter().filter(|p| inside.contains(p)).count();
    assert!(
        !between.is_empty(),
        "no unseen move lies between two seen ones"
    );
    assert!(
        trusted_between * 2 >= between.len(),
        "only {trusted_between} of {} unseen safe moves between seen ones are trusted",
        between.len()
    );
    let unseen_trusted = inside.iter().filter(|p| !executed.contains(p)).count();
    assert!(unseen_trusted > 0, "only executed moves are trusted");

    // Exploration: after β turned positive the robot still executed moves it had not, and the
    // precondition grew.
    let before = at_first_positive.unwrap();
    let new_moves = executed.difference(&executed_before_positive).count();
    assert!(new_moves > 0, "nothing new executed once β > 0");
    assert!(
        inside.len() > before.len() && !inside.is_subset(&before),
        "the precondition did not grow once β > 0: {} → {} trusted",
        before.len(),
        inside.len()
    );

    // The curve improves.
    let (first, last) = (success_first.unwrap(), l.success(&test_problems).await);
    assert!(
        last > first,
        "test success {first:.2} after the first batch, {last:.2} at the end"
    );
    eprintln!(
        "trusted {} (before β > 0: {}), unseen trusted {unseen_trusted}, between {trusted_between}/{}, \
         unsafe trusted {}/{}, new moves after β > 0 {new_moves}, success {first:.2} → {last:.2}",
        inside.len(),
        before.len(),
        between.len(),
        unsafe_inside.len(),
        unsafe_pairs.len()
    );
}
