//! How a proposal's candidates are compared — the planner's RRT candidates and a client's posted
//! ones alike ([`value_candidates`]): each candidate's score by the acquisition function
//! (`lcb`, `level_set`; σ fantasised over the state-actions in flight under `active`), and,
//! under `active`, the value an [`Acquisition`] puts on executing it (`bottleneck`: the problems
//! it would open; `spread`: the boundary uncertainty it would remove), which decides where any
//! candidate is worth something.
//!
//! A new value-based acquisition is an [`Acquisition`] implementation and an arm in
//! [`of_kind`].

use super::acquisition::AcquisitionKind;
use super::bottleneck;
use super::cache::ModelCache;
use super::error::PlanningError;
use super::model::DeviationModel;
use super::rrt::Task;
use super::spread;
use super::trajectory::Trajectory;
use crate::budget::Budget;

/// What an [`Acquisition`] values candidates in: the task (domain, problem, precondition,
/// settings), the deviation model, the state-actions in flight, the proposal's seed and its
/// budget.
#[derive(Clone, Copy)]
pub(crate) struct Context<'a> {
    /// The problem and the precondition the candidates were found for.
    pub task: Task<'a>,
    /// The deviation model.
    pub model: &'a dyn DeviationModel,
    /// Features of the state-actions executed or chosen since the model was fitted.
    pub in_flight: &'a [f64],
    /// The proposal's seed.
    pub seed: u64,
    /// The proposal's budget.
    pub budget: &'a Budget,
}

/// A value-based acquisition: what executing each candidate is worth (larger is better), or
/// `None` where it cannot value these candidates (then the score decides).
pub(crate) trait Acquisition {
    /// Each candidate's value, in order; may add candidates of its own to `trajectories` (with
    /// their values) where `probe` allows.
    fn values(
        &self,
        context: Context<'_>,
        cache: &mut ModelCache<'_>,
        trajectories: &mut Vec<Trajectory>,
        probe: Probe,
    ) -> Result<Option<Vec<f64>>, PlanningError>;
}

/// `lcb` and `level_set`: no value beyond the score.
struct ByScore;

impl Acquisition for ByScore {
    fn values(
        &self,
        _context: Context<'_>,
        _cache: &mut ModelCache<'_>,
        _trajectories: &mut Vec<Trajectory>,
        _probe: Probe,
    ) -> Result<Option<Vec<f64>>, PlanningError> {
        Ok(None)
    }
}

/// `bottleneck` ([`bottleneck::assess`]): the problems a candidate's steps would open; its probe
/// (the way to the most valuable untrusted step) joins the candidates where allowed.
struct Bottleneck;

impl Acquisition for Bottleneck {
    fn values(
        &self,
        context: Context<'_>,
        cache: &mut ModelCache<'_>,
        trajectories: &mut Vec<Trajectory>,
        probe: Probe,
    ) -> Result<Option<Vec<f64>>, PlanningError> {
        let Context {
            task,
            in_flight,
            seed,
            budget,
            ..
        } = context;
        Ok(
            bottleneck::assess(task, cache, trajectories, in_flight, seed, budget)?.map(
                |assessment| {
                    let mut values = assessment.values;
                    if let Some((found, value)) = assessment.probe
                        && value > 0.0
                        && probe == Probe::Allowed
                    {
                        trajectories.push(found);
                        values.push(value);
                    }
                    values
                },
            ),
        )
    }
}

/// `spread` ([`spread::values`]): the boundary uncertainty a candidate's execution would remove.
struct Spread;

impl Acquisition for Spread {
    fn values(
        &self,
        context: Context<'_>,
        _cache: &mut ModelCache<'_>,
        trajectories: &mut Vec<Trajectory>,
        _probe: Probe,
    ) -> Result<Option<Vec<f64>>, PlanningError> {
        let Context {
            task,
            model,
            in_flight,
            seed,
            budget,
        } = context;
        spread::values(task, model, in_flight, trajectories, seed, budget)
    }
}

/// The [`Acquisition`] of a `learning.acquisition` setting.
pub(crate) fn of_kind(kind: AcquisitionKind) -> &'static dyn Acquisition {
    match kind {
        AcquisitionKind::Lcb | AcquisitionKind::LevelSet => &ByScore,
        AcquisitionKind::Bottleneck => &Bottleneck,
        AcquisitionKind::Spread => &Spread,
    }
}

/// How a set of candidates was valued, whoever found them ([`value_candidates`]).
pub(crate) struct Valuation {
    /// Each candidate's `α_step` per step and `α` by the acquisition's score (`lcb`, or
    /// `level_set`; σ fantasised with the state-actions in flight under `active`).
    pub scored: Vec<(Vec<f64>, f64)>,
    /// Each candidate's `α` as the strategy compares them (smallest chosen): the score's, or
    /// for a value-based acquisition that valued any candidate above 0, the value negated
    /// (the score then only breaks exact ties).
    pub alphas: Vec<f64>,
    /// The rule that decided the comparison: the experiment's acquisition, or `lcb` where a
    /// value-based one could not value these candidates (no graph, an exhausted budget, no
    /// value above 0) or the strategy is not `active`.
    pub valued_by: AcquisitionKind,
}

/// Whether [`value_candidates`] may add `bottleneck`'s probe (a trajectory towards the most
/// valuable step) to the candidates: yes for the planner's own, no for a client's, which it
/// must choose among as posted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Probe {
    /// The probe may join the candidates.
    Allowed,
    /// The candidates stay as given.
    Refused,
}

/// The one valuation of a proposal's candidates, the planner's RRT candidates and a client's
/// posted ones alike: under `active` the experiment's [`Acquisition`] values each candidate
/// (`bottleneck`, `spread`) and compares by value where any is above 0; every other case
/// compares the acquisition's score (with σ fantasised over `in_flight` under `active`).
/// `active`: whether the strategy compares by the acquisition (`goal_conditioned` and `random`
/// choose at random among the eligible; their candidates carry the score alone).
pub(crate) fn value_candidates(
    context: Context<'_>,
    cache: &mut ModelCache<'_>,
    trajectories: &mut Vec<Trajectory>,
    active: bool,
    probe: Probe,
) -> Result<Valuation, PlanningError> {
    let Context {
        task,
        model,
        in_flight,
        ..
    } = context;
    let acquisition = task.settings.acquisition();
    let values = if active {
        of_kind(acquisition.kind).values(context, cache, trajectories, probe)?
    } else {
        None
    };
    let scored: Vec<(Vec<f64>, f64)> = if active && !in_flight.is_empty() {
        fantasised_scores(task, model, in_flight, trajectories)?
    } else {
        trajectories
            .iter()
            .map(|t| acquisition.score(t, task.precondition.d_max()))
            .collect()
    };
    Ok(compare(acquisition.kind, scored, values))
}

/// The comparison of candidates scored `scored` and valued `values` by an acquisition of
/// `kind`: by value where any is above 0 (the score then only breaks exact ties), else by
/// the score (`bottleneck` and `spread` score by `lcb`).
pub(crate) fn compare(
    kind: AcquisitionKind,
    scored: Vec<(Vec<f64>, f64)>,
    values: Option<Vec<f64>>,
) -> Valuation {
    let mut alphas: Vec<f64> = scored.iter().map(|(_, alpha)| *alpha).collect();
    let mut valued_by = match kind {
        AcquisitionKind::Bottleneck | AcquisitionKind::Spread => AcquisitionKind::Lcb,
        kind => kind,
    };
    if let Some(values) = values
        && values.iter().any(|v| *v > 0.0)
    {
        for (alpha, v) in alphas.iter_mut().zip(&values) {
            *alpha = -v + 1e-9 * alpha.tanh();
        }
        valued_by = kind;
    }
    Valuation {
        scored,
        alphas,
        valued_by,
    }
}

/// The acquisition of each candidate (`α_step` per step and `α`) with each step's σ as if the
/// state-actions `in_flight` were labelled already ([`DeviationModel::predict_fantasised`];
/// μ as planned): a step near what the batch has already executed or chosen promises less. One
/// call to the model for every step of every candidate.
fn fantasised_scores(
    task: Task<'_>,
    model: &dyn DeviationModel,
    in_flight: &[f64],
    trajectories: &[Trajectory],
) -> Result<Vec<(Vec<f64>, f64)>, PlanningError> {
    let (domain, d_max) = (task.domain, task.precondition.d_max());
    let dim = domain.feature_dim();
    let features: Vec<f64> = trajectories
        .iter()
        .flat_map(|t| t.steps())
        .flat_map(|(s, a, next)| domain.features(s, a, next))
        .collect();
    let expected = trajectories.iter().map(Trajectory::len).sum::<usize>();
    let answers = model.predict_fantasised(&features, in_flight, dim);
    if answers.len() != expected {
        return Err(PlanningError::ModelOutput {
            expected,
            got: answers.len(),
        });
    }
    let mut answers = answers.into_iter();
    Ok(trajectories
        .iter()
        .map(|t| {
            let fantasy = Trajectory {
                sigma: answers.by_ref().take(t.len()).map(|(_, s)| s).collect(),
                ..t.clone()
            };
            task.settings.acquisition().score(&fantasy, d_max)
        })
        .collect())
}
