//! The `spread` acquisition's value of a candidate: the uncertainty about the precondition's
//! boundary its execution would remove across the whole space, not only along itself.
//!
//! Per executed transition, short random rollouts teach the MDE far more than planned
//! trajectories early on (docs/research/active-selection.md, "Continuous worlds at equal
//! cost"): they spread over the space, while planned candidates follow the corridors between
//! starts and goals. A candidate's value is therefore a *targeted integrated variance
//! reduction* (the tIMSE criterion of contour estimation): over [`REFERENCES`] state-actions
//! drawn uniformly from the domain,
//!
//! `V = Σ_x w(x) (σ²(x) − σ²(x | the candidate's steps labelled))`,
//! `w(x) = φ((d_max − μ(x)) / σ(x)) / σ(x)`,
//!
//! the density of `d_max` under the model's Gaussian at `x`: a point whose side of `d_max` is
//! already clear counts little, one near the level set counts much. The σ after labelling is
//! fantasised ([`DeviationModel::predict_fantasised`], exact for a GP: its variance does not
//! depend on the labels), with the state-actions in flight counted as labelled in both terms;
//! the references are prepared once for every candidate ([`DeviationModel::fantasy`]: the exact
//! GP whitens them once).
//! A model that cannot fantasise values every candidate 0, and the choice is then `lcb`'s.

use super::error::PlanningError;
use super::model::DeviationModel;
use super::rrt::Task;
use super::trajectory::Trajectory;
use crate::budget::Budget;
use crate::domain::DynamicsModel;
use crate::planning::rrt::{predict_with, predictions_with, seeded_rng};

/// State-actions the value is integrated over.
pub const REFERENCES: usize = 256;

/// Stream of the proposal seed the reference state-actions are drawn from.
const REFERENCE_STREAM: u64 = 7;

/// Candidates valued in one call of the model's [`fantasy`](DeviationModel::fantasy): the
/// exact GP reads its `n × n` factor once per call, and the budget is checked between calls.
const CANDIDATES_PER_CALL: usize = 5;

/// Each candidate's value `V` (see the module docs), in order; `None` when the budget ends
/// before every candidate is valued (the choice is then `lcb`'s, as for a model that cannot
/// fantasise), so that a large model never turns a proposal into a missed deadline.
pub(crate) fn values(
    task: Task<'_>,
    model: &dyn DeviationModel,
    in_flight: &[f64],
    trajectories: &[Trajectory],
    seed: u64,
    budget: &Budget,
) -> Result<Option<Vec<f64>>, PlanningError> {
    let own = SpreadModel {
        dynamics: task.domain.dynamics(),
        deviation: model,
        in_flight,
    };
    values_across(task, &[own], trajectories, &[], seed, budget)
}

/// One model whose precondition an execution teaches: its dynamics (what its features read),
/// its deviation model and the features of its state-actions in flight.
#[derive(Clone, Copy)]
pub(crate) struct SpreadModel<'a> {
    /// The dynamics model `f̂_m`.
    pub dynamics: &'a dyn DynamicsModel,
    /// The deviation model of `f̂_m`'s precondition.
    pub deviation: &'a dyn DeviationModel,
    /// Features (with `f̂_m`'s predictions) of the state-actions in flight.
    pub in_flight: &'a [f64],
}

/// [`values`] for an execution that labels every model of `models` at once: each candidate's
/// value is the sum over the models of the boundary uncertainty its steps would remove from
/// that model's precondition, each model's references and each candidate's steps featured
/// with that model's predictions. `step_models[i][k]` is the model (an index into `models`)
/// whose prediction step `k` of candidate `i` carries; empty: every step carries the first
/// model's. `None` when the budget ends before every model valued every candidate.
pub(crate) fn values_across(
    task: Task<'_>,
    models: &[SpreadModel<'_>],
    trajectories: &[Trajectory],
    step_models: &[Vec<usize>],
    seed: u64,
    budget: &Budget,
) -> Result<Option<Vec<f64>>, PlanningError> {
    let domain = task.domain;
    let mut rng = seeded_rng(seed, REFERENCE_STREAM);
    let sampled: Vec<(Vec<f64>, Vec<f64>)> = (0..REFERENCES)
        .map(|_| {
            let s = domain.sample_state(&mut rng);
            let a = domain.sample_action(&s, &mut rng);
            (s, a)
        })
        .collect();
    let mut total = vec![0.0; trajectories.len()];
    for (m, model) in models.iter().enumerate() {
        let pendings = pendings_of(task, m, model.dynamics, trajectories, step_models, budget)?;
        let Some(values) = values_of(task, *model, &sampled, &pendings, budget)? else {
            return Ok(None);
        };
        for (t, v) in total.iter_mut().zip(values) {
            *t += v;
        }
    }
    Ok(Some(total))
}

/// Each candidate's steps featured with model `m`'s predictions: the trajectory's own where
/// its step carries `m`'s, else `m`'s asked in one call (only when the domain's features read
/// the prediction).
fn pendings_of(
    task: Task<'_>,
    m: usize,
    dynamics: &dyn DynamicsModel,
    trajectories: &[Trajectory],
    step_models: &[Vec<usize>],
    budget: &Budget,
) -> Result<Vec<Vec<f64>>, PlanningError> {
    let domain = task.domain;
    let carries = |i: usize, k: usize| step_models.get(i).is_none_or(|sm| sm[k] == m);
    let mut asked: (Vec<&[f64]>, Vec<&[f64]>) = (Vec::new(), Vec::new());
    if domain.features_use_prediction() {
        for (i, t) in trajectories.iter().enumerate() {
            for (k, (s, a, _)) in t.steps().enumerate() {
                if !carries(i, k) {
                    asked.0.push(s);
                    asked.1.push(a);
                }
            }
        }
    }
    let mut calls = 0;
    let mut predicted =
        predict_with(domain, dynamics, &asked.0, &asked.1, &mut calls, budget, 0)?.into_iter();
    Ok(trajectories
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let mut pending = Vec::new();
            for (k, (s, a, next)) in t.steps().enumerate() {
                if carries(i, k) || !domain.features_use_prediction() {
                    pending.extend(domain.features(s, a, next));
                } else {
                    let p = predicted.next().expect("one prediction per step asked");
                    pending.extend(domain.features(s, a, &p.next));
                }
            }
            pending
        })
        .collect())
}

/// One model's value of each candidate (its steps' features `pendings`), over the reference
/// state-actions `sampled` featured with its predictions.
fn values_of(
    task: Task<'_>,
    model: SpreadModel<'_>,
    sampled: &[(Vec<f64>, Vec<f64>)],
    pendings: &[Vec<f64>],
    budget: &Budget,
) -> Result<Option<Vec<f64>>, PlanningError> {
    let (domain, d_max) = (task.domain, task.precondition.d_max());
    let dim = domain.feature_dim();
    let predicted = predictions_with(domain, model.dynamics, sampled, budget)?;
    let mut references = Vec::with_capacity(REFERENCES * dim);
    for ((s, a), next) in sampled.iter().zip(&predicted) {
        references.extend(domain.features(s, a, next));
    }
    let fantasy = model.deviation.fantasy(&references, dim);
    let predict = |pendings: &[&[f64]]| {
        let answers = fantasy(pendings);
        let wrong = (answers.len() != pendings.len())
            .then_some(answers.len())
            .or_else(|| answers.iter().map(Vec::len).find(|&n| n != REFERENCES));
        match wrong {
            None => Ok(answers),
            Some(got) => Err(PlanningError::ModelOutput {
                expected: REFERENCES,
                got,
            }),
        }
    };
    let now = predict(&[model.in_flight])?.swap_remove(0);
    let weights: Vec<f64> = now
        .iter()
        .map(|&(mu, sigma)| level_density(mu, sigma, d_max))
        .collect();
    let mut values = Vec::with_capacity(pendings.len());
    for chunk in pendings.chunks(CANDIDATES_PER_CALL) {
        if budget.stop().is_some() {
            return Ok(None);
        }
        let with_flight: Vec<Vec<f64>> = chunk
            .iter()
            .map(|steps| [model.in_flight, steps].concat())
            .collect();
        let sets: Vec<&[f64]> = with_flight.iter().map(Vec::as_slice).collect();
        for after in predict(&sets)? {
            let value: f64 = weights
                .iter()
                .zip(&now)
                .zip(&after)
                .map(|((w, (_, s0)), (_, s1))| w * (s0 * s0 - s1 * s1).max(0.0))
                .sum();
            // A model answer that is not a number values the candidate at nothing.
            values.push(if value.is_finite() { value } else { 0.0 });
        }
    }
    Ok(Some(values))
}

/// `φ((d_max − μ)/σ) / σ`, the density of `d_max` under `N(μ, σ²)` (without the `1/√(2π)`,
/// which no comparison needs); 0 for a σ that is not positive.
fn level_density(mu: f64, sigma: f64, d_max: f64) -> f64 {
    if sigma > 0.0 && sigma.is_finite() {
        let z = (d_max - mu) / sigma;
        (-0.5 * z * z).exp() / sigma
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::{Domain, Kinematic, KinematicParams, Problem};
    use crate::planning::{PlanningSettings, Precondition};

    /// μ rises across the first state feature and reaches `d_max` = 0.1 at 0.5; σ is 0.05, or
    /// 0.005 within 0.1 (in the state features) of a labelled state-action.
    struct Boundary;

    impl Boundary {
        fn answer(x: &[f64], labelled: &[f64], dim: usize) -> (f64, f64) {
            let near = labelled
                .chunks(dim)
                .any(|p| (p[0] - x[0]).hypot(p[1] - x[1]) < 0.1);
            (0.2 * x[0], if near { 0.005 } else { 0.05 })
        }
    }

    impl DeviationModel for Boundary {
        fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
            self.predict_fantasised(features, &[], dim)
        }

        fn predict_fantasised(
            &self,
            features: &[f64],
            pending: &[f64],
            dim: usize,
        ) -> Vec<(f64, f64)> {
            features
                .chunks(dim)
                .map(|x| Self::answer(x, pending, dim))
                .collect()
        }
    }

    /// A vertical walk at `x` from y = 0.1 to 0.9 in steps of 0.1.
    fn walk(x: f64) -> Trajectory {
        let states: Vec<Vec<f64>> = (1..=9).map(|k| vec![x, 0.1 * k as f64]).collect();
        let n = states.len() - 1;
        Trajectory {
            actions: vec![vec![0.0, 0.1]; n],
            mu: vec![0.0; n],
            sigma: vec![0.05; n],
            states,
        }
    }

    #[test]
    fn a_walk_along_the_boundary_is_worth_more_than_one_where_the_side_is_clear() {
        let domain = Kinematic::new(KinematicParams::default()).unwrap();
        let problem = Problem::new(&domain, vec![0.5, 0.1], vec![0.5, 0.9]).unwrap();
        let settings = PlanningSettings::default();
        let task = Task {
            domain: &domain,
            problem: &problem,
            precondition: Precondition::new(2.0, 0.1).unwrap(),
            settings: &settings,
        };
        let walks = [walk(0.05), walk(0.5), walk(0.95)];
        let v = values(task, &Boundary, &[], &walks, 3, &Budget::unlimited())
            .unwrap()
            .unwrap();
        assert!(v.iter().all(|x| *x >= 0.0), "{v:?}");
        // The weight at x = 0.5 (μ = d_max) is e^{1.8²/2} ≈ 5 times that at x = 0.05 or 0.95
        // (μ 1.8 σ from d_max), and each walk settles σ over as many references.
        assert!(
            v[1] > 3.0 * v[0] && v[1] > 3.0 * v[2],
            "along μ = d_max the walk settles most: {v:?}"
        );
        // Steps already in flight teach nothing new: the same walk then is worth nothing.
        let mut in_flight = Vec::new();
        for (s, a, next) in walks[1].steps() {
            in_flight.extend(domain.features(s, a, next));
        }
        let again = values(
            task,
            &Boundary,
            &in_flight,
            &walks[1..2],
            3,
            &Budget::unlimited(),
        )
        .unwrap();
        assert_eq!(again, Some(vec![0.0]));
        // A model that cannot fantasise values every candidate at nothing (`lcb` chooses).
        let flat = crate::planning::synthetic::ConstantModel {
            mu: 0.05,
            sigma: 0.05,
        };
        let none = values(task, &flat, &[], &walks, 3, &Budget::unlimited()).unwrap();
        assert_eq!(none, Some(vec![0.0; 3]));
        // A budget already spent values nothing, and the proposal is still answered (by `lcb`).
        let spent = Budget::unlimited().cancelled_by(std::sync::Arc::new(
            std::sync::atomic::AtomicBool::new(true),
        ));
        assert_eq!(
            values(task, &Boundary, &[], &walks, 3, &spent).unwrap(),
            None
        );
        // More candidates than one call values: each still gets its own value, in order.
        let many: Vec<Trajectory> = (1..=2 * CANDIDATES_PER_CALL + 1)
            .map(|k| walk(k as f64 / 12.0))
            .collect();
        let all = values(task, &Boundary, &[], &many, 3, &Budget::unlimited())
            .unwrap()
            .unwrap();
        let alone: Vec<f64> = many
            .iter()
            .map(|t| {
                values(
                    task,
                    &Boundary,
                    &[],
                    std::slice::from_ref(t),
                    3,
                    &Budget::unlimited(),
                )
                .unwrap()
                .unwrap()[0]
            })
            .collect();
        assert_eq!(all, alone);
    }

    /// `Boundary` turned a quarter: its boundary runs along y = 0.5.
    struct Across;

    impl DeviationModel for Across {
        fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
            self.predict_fantasised(features, &[], dim)
        }

        fn predict_fantasised(
            &self,
            features: &[f64],
            pending: &[f64],
            dim: usize,
        ) -> Vec<(f64, f64)> {
            let turn = |x: &[f64]| {
                let mut t = x.to_vec();
                t.swap(0, 1);
                t
            };
            let pending: Vec<f64> = pending.chunks(dim).flat_map(turn).collect();
            features
                .chunks(dim)
                .map(|x| Boundary::answer(&turn(x), &pending, dim))
                .collect()
        }
    }

    #[test]
    fn an_execution_that_labels_two_models_is_worth_what_it_teaches_each() {
        let domain = Kinematic::new(KinematicParams::default()).unwrap();
        let problem = Problem::new(&domain, vec![0.5, 0.1], vec![0.5, 0.9]).unwrap();
        let settings = PlanningSettings::default();
        let task = Task {
            domain: &domain,
            problem: &problem,
            precondition: Precondition::new(2.0, 0.1).unwrap(),
            settings: &settings,
        };
        let walks = [walk(0.05), walk(0.5), walk(0.95)];
        let unlimited = Budget::unlimited();
        let alone = |model: &dyn DeviationModel| {
            values(task, model, &[], &walks, 3, &unlimited)
                .unwrap()
                .unwrap()
        };
        let model = |deviation: &'static dyn DeviationModel| SpreadModel {
            dynamics: domain.dynamics(),
            deviation,
            in_flight: &[],
        };
        let both = values_across(
            task,
            &[model(&Boundary), model(&Across)],
            &walks,
            &[],
            3,
            &unlimited,
        )
        .unwrap()
        .unwrap();
        let (b, a) = (alone(&Boundary), alone(&Across));
        assert_eq!(both, vec![b[0] + a[0], b[1] + a[1], b[2] + a[2]]);
        // Each vertical walk crosses `Across`'s boundary alike, so it adds to each walk
        // without deciding between them; `Boundary`'s still does.
        assert!(a.iter().all(|v| *v > 0.0), "{a:?}");
        assert!(both[1] > both[0] && both[1] > both[2], "{both:?}");
        // A model with nothing to fantasise adds nothing.
        let flat = crate::planning::synthetic::ConstantModel {
            mu: 0.05,
            sigma: 0.05,
        };
        let with_flat = values_across(
            task,
            &[
                model(&Boundary),
                SpreadModel {
                    dynamics: domain.dynamics(),
                    deviation: &flat,
                    in_flight: &[],
                },
            ],
            &walks,
            &[],
            3,
            &unlimited,
        )
        .unwrap()
        .unwrap();
        assert_eq!(with_flat, b);
    }

    #[test]
    fn the_level_set_weighs_most_where_the_side_is_least_clear() {
        let d_max = 0.1;
        let on = level_density(0.1, 0.02, d_max);
        let near = level_density(0.12, 0.02, d_max);
        let far = level_density(0.3, 0.02, d_max);
        assert!(on > near && near > far, "{on} {near} {far}");
        assert!(far < 1e-20);
        assert_eq!(level_density(0.1, 0.0, d_max), 0.0);
        assert_eq!(level_density(0.1, f64::NAN, d_max), 0.0);
    }
}
