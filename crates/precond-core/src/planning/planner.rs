//! The planner's front door: a [`Planner`] holds what stays fixed while an experiment plans —
//! its domain, its deviation model, its checked [`PlanningSettings`] and the search's
//! [`Budget`] — and answers for checked values: a [`Problem`] and a [`Precondition`].
//!
//! ```
//! use precond_core::domain::{Domain, IcyGridworld, Problem};
//! use precond_core::planning::{Planner, PlanningSettings, Precondition, Strategy};
//! use precond_core::planning::synthetic::ConstantModel;
//!
//! let grid = IcyGridworld::default_layout();
//! let model = ConstantModel { mu: 0.0, sigma: 0.01 };
//! let settings = PlanningSettings::default();
//! let planner = Planner::new(&grid, &model, &settings);
//! let problem = Problem::new(&grid, vec![0.0, 0.0], vec![3.0, 0.0]).unwrap();
//! let proposal = planner
//!     .propose(Strategy::Active, &problem, Precondition::new(2.0, 0.1).unwrap(), 7)
//!     .unwrap();
//! assert!(grid.is_goal(proposal.trajectory.states.last().unwrap(), problem.goal()));
//! ```

use super::acquisition::AcquisitionKind;
use super::cache::ModelCache;
use super::error::PlanningError;
use super::given::{self, Path, Verdict};
use super::model::{DeviationModel, PlanModel};
use super::precondition::Precondition;
use super::rrt::{self, RrtOutcome, Stage, Task};
pub use super::settings::PlanningSettings;
use super::strategy::{self, Proposal, Strategy};
use super::trajectory::Trajectory;
use super::valuation;
use crate::budget::Budget;
use crate::domain::{Domain, Problem};
use rand::RngCore;

/// Plans in one domain with one deviation model under checked settings, within a budget
/// (unlimited unless [`within`](Self::within) says otherwise). Cheap to build: it only borrows.
/// Every answer is determined by its inputs and `seed`.
///
/// It is the top of the module: the searches ([`rrt`](mod@super::rrt)), the strategies
/// ([`strategy`](mod@super::strategy)) and the judging of given candidates
/// ([`given`](mod@super::given)) are handed the values they need (a task of the problem, the
/// precondition and the settings; the deviation model; the budget), never the planner.
#[derive(Clone)]
pub struct Planner<'a> {
    domain: &'a dyn Domain,
    model: &'a dyn DeviationModel,
    settings: &'a PlanningSettings,
    budget: Budget,
    in_flight: &'a [f64],
}

impl<'a> Planner<'a> {
    /// A planner with no deadline.
    pub fn new(
        domain: &'a dyn Domain,
        model: &'a dyn DeviationModel,
        settings: &'a PlanningSettings,
    ) -> Self {
        Self {
            domain,
            model,
            settings,
            budget: Budget::unlimited(),
            in_flight: &[],
        }
    }

    /// The same planner stopping with [`PlanningError::Stopped`] once `budget` says so.
    pub fn within(mut self, budget: Budget) -> Self {
        self.budget = budget;
        self
    }

    /// The same planner knowing the features (row-major, the domain's feature dimension each)
    /// of the state-actions executed or chosen since its deviation model was fitted: `active`
    /// scores its candidates as if those were labelled already
    /// ([`DeviationModel::predict_fantasised`]), so one batch's trajectories do not chase the
    /// same uncertainty. Trust is judged by the model as it is.
    pub fn with_in_flight(mut self, features: &'a [f64]) -> Self {
        self.in_flight = features;
        self
    }

    /// What the searches of one answer for `problem` inside `precondition` share.
    pub(crate) fn task<'p>(&self, problem: &'p Problem, precondition: Precondition) -> Task<'p>
    where
        'a: 'p,
    {
        Task {
            domain: self.domain,
            problem,
            precondition,
            settings: self.settings,
        }
    }

    /// One RRT run inside `precondition`, `rng` driving every random choice (see
    /// [`rrt`](mod@super::rrt)).
    pub fn rrt(
        &self,
        problem: &Problem,
        precondition: Precondition,
        rng: &mut dyn RngCore,
    ) -> Result<RrtOutcome, PlanningError> {
        let mut cache = ModelCache::new(self.model, self.domain.feature_dim());
        rrt::grow(
            self.task(problem, precondition),
            &mut cache,
            rng,
            &self.budget,
        )
    }

    /// The test-time plan: one RRT run inside `precondition` (the conservative test β),
    /// seeded by `seed`. `trajectory` is `None` when no plan was found within
    /// `max_extensions`.
    pub fn plan(
        &self,
        problem: &Problem,
        precondition: Precondition,
        seed: u64,
    ) -> Result<RrtOutcome, PlanningError> {
        self.rrt(problem, precondition, &mut rrt::seeded_rng(seed, 0))
    }

    /// The test-time plan stepping with several models: one RRT run in which each step may
    /// rely on a different model of `models` — the cheapest whose own precondition (its
    /// deviation model, `precondition`) trusts the step, each asked only about the actions
    /// no cheaper model trusted — seeded by `seed`. The outcome's `step_models` name the
    /// model of each step and `model_calls` the calls to each (indexes into `models`, given in
    /// any order; equal costs are tried in the given order). With the domain's model and
    /// the planner's deviation model alone, it is [`plan`](Self::plan).
    pub fn plan_across(
        &self,
        problem: &Problem,
        precondition: Precondition,
        models: &[PlanModel<'_>],
        seed: u64,
    ) -> Result<RrtOutcome, PlanningError> {
        let order = cost_order(models)?;
        let dim = self.domain.feature_dim();
        let mut caches: Vec<ModelCache<'_>> = order
            .iter()
            .map(|&i| ModelCache::new(models[i].deviation, dim))
            .collect();
        let mut stages: Vec<Stage<'_, '_>> = order
            .iter()
            .zip(caches.iter_mut())
            .map(|(&i, cache)| Stage {
                dynamics: models[i].dynamics,
                cache,
            })
            .collect();
        let mut outcome = rrt::grow_across(
            self.task(problem, precondition),
            &mut stages,
            vec![rrt::seeded_rng(seed, 0)],
            &self.budget,
        )?
        .pop()
        .expect("one search, one outcome");
        for m in &mut outcome.step_models {
            *m = order[*m];
        }
        let mut calls = vec![0; models.len()];
        for (k, &i) in order.iter().enumerate() {
            calls[i] = outcome.model_calls[k];
        }
        outcome.model_calls = calls;
        Ok(outcome)
    }

    /// The proposal of `strategy` (`active` or `goal_conditioned`) when an execution labels
    /// every model of `models` (given in any order, as for [`plan_across`](Self::plan_across)):
    /// candidates that step, each step, with the cheapest model whose precondition trusts it,
    /// valued under `spread` by what their execution would teach every model's precondition
    /// (`in_flight[m]`: the features, with model `m`'s predictions, of its state-actions in
    /// flight). Tried inside each precondition of `ladder` in turn, as
    /// [`propose_relaxing`](Self::propose_relaxing). The proposal's `step_models` index into
    /// `models`. The planner's own deviation model and state-actions in flight are not used.
    pub fn propose_across(
        &self,
        strategy: Strategy,
        problem: &Problem,
        ladder: &[Precondition],
        models: &[PlanModel<'_>],
        in_flight: &[&[f64]],
        seed: u64,
    ) -> Result<Proposal, PlanningError> {
        let order = cost_order(models)?;
        let sorted: Vec<PlanModel<'_>> = order.iter().map(|&i| models[i]).collect();
        if in_flight.len() != models.len() {
            return Err(PlanningError::input(
                "in_flight",
                format!("{} sets for {} models", in_flight.len(), models.len()),
            ));
        }
        let flights: Vec<&[f64]> = order.iter().map(|&i| in_flight[i]).collect();
        let mut proposal = relax(
            ladder,
            |p: &mut Proposal, spent| p.extensions += spent,
            |precondition| match strategy::propose_across(
                self.task(problem, precondition),
                &sorted,
                &flights,
                &self.budget,
                strategy,
                seed,
            ) {
                Ok(p) => Ok(Rung::Taken(p)),
                Err(PlanningError::NoPlan { extensions }) => Ok(Rung::Passed {
                    extensions,
                    answer: None,
                }),
                Err(e) => Err(e),
            },
        )?;
        for m in &mut proposal.step_models {
            *m = order[*m];
        }
        Ok(proposal)
    }

    /// The trajectory `strategy` chooses for the robot to execute next for `problem` inside
    /// `precondition` (see [`strategy`](mod@super::strategy)).
    pub fn propose(
        &self,
        strategy: Strategy,
        problem: &Problem,
        precondition: Precondition,
        seed: u64,
    ) -> Result<Proposal, PlanningError> {
        strategy::propose(
            self.task(problem, precondition),
            self.model,
            &self.budget,
            strategy,
            seed,
            self.in_flight,
        )
    }

    /// [`propose`](Self::propose) inside each precondition of `ladder` in turn (a
    /// [`relaxation_ladder`](super::relaxation_ladder)'s βs) until one has a trajectory; the
    /// proposal's `beta` says which, and its `extensions` count the attempts before it too.
    /// [`PlanningError::NoPlan`] only when none has a plan, with the extensions of every
    /// attempt; any other error ends the search at once. The planner's one budget bounds all
    /// attempts.
    pub fn propose_relaxing(
        &self,
        strategy: Strategy,
        problem: &Problem,
        ladder: &[Precondition],
        seed: u64,
    ) -> Result<Proposal, PlanningError> {
        relax(
            ladder,
            |p: &mut Proposal, spent| p.extensions += spent,
            |precondition| match self.propose(strategy, problem, precondition, seed) {
                Ok(p) => Ok(Rung::Taken(p)),
                Err(PlanningError::NoPlan { extensions }) => Ok(Rung::Passed {
                    extensions,
                    answer: None,
                }),
                Err(e) => Err(e),
            },
        )
    }

    /// [`judge`](Self::judge), then the eligible candidates valued as `strategy` compares them
    /// — by the experiment's acquisition, as the planner's own candidates are
    /// ([`valuation::value_candidates`]; `bottleneck` adds no probe to a client's candidates) —
    /// within the planner's budget and with its state-actions in flight. Each eligible
    /// verdict's `alpha` (and `alpha_step`) is then the value compared; the answer says which
    /// rule that was.
    pub fn judge_valued(
        &self,
        problem: &Problem,
        candidates: Vec<Path>,
        precondition: Precondition,
        strategy: Strategy,
        seed: u64,
    ) -> Result<(Vec<Verdict>, AcquisitionKind), PlanningError> {
        let mut verdicts = self.judge(problem.goal(), candidates, precondition)?;
        let eligible: Vec<usize> = (0..verdicts.len())
            .filter(|&i| verdicts[i].eligible())
            .collect();
        let mut trajectories: Vec<Trajectory> = eligible
            .iter()
            .map(|&i| verdicts[i].trajectory.clone())
            .collect();
        let mut cache = ModelCache::new(self.model, self.domain.feature_dim());
        let valuation = valuation::value_candidates(
            valuation::Context {
                task: self.task(problem, precondition),
                model: self.model,
                in_flight: self.in_flight,
                seed,
                budget: &self.budget,
            },
            &mut cache,
            &mut trajectories,
            strategy == Strategy::Active,
            valuation::Probe::Refused,
        )?;
        for ((&i, (alpha_step, _)), alpha) in
            eligible.iter().zip(valuation.scored).zip(valuation.alphas)
        {
            verdicts[i].alpha_step = alpha_step;
            verdicts[i].alpha = alpha;
        }
        Ok((verdicts, valuation.valued_by))
    }

    /// [`judge_valued`](Self::judge_valued) inside each precondition of `ladder` in turn
    /// until `strategy` has a candidate to choose ([`given::choose`]) — the β relaxation of
    /// [`propose_relaxing`](Self::propose_relaxing) for a client's candidates, within the
    /// planner's one budget. Answers the verdicts of the precondition it stopped at (the last
    /// one when none had a choice), the rule that valued them, that precondition and the
    /// chosen index (`None`: no plan at any β).
    pub fn judge_relaxing(
        &self,
        problem: &Problem,
        candidates: Vec<Path>,
        ladder: &[Precondition],
        strategy: Strategy,
        seed: u64,
    ) -> Result<GivenChoice, PlanningError> {
        if ladder.is_empty() {
            return Err(PlanningError::input(
                "ladder",
                "no precondition to judge inside",
            ));
        }
        relax(
            ladder,
            |_, _| {},
            |precondition| {
                let (verdicts, valued_by) =
                    self.judge_valued(problem, candidates.clone(), precondition, strategy, seed)?;
                let chosen = given::choose(strategy, &verdicts, seed);
                let answer = GivenChoice {
                    verdicts,
                    valued_by,
                    precondition,
                    chosen,
                };
                Ok(match chosen {
                    Some(_) => Rung::Taken(answer),
                    None => Rung::Passed {
                        extensions: 0,
                        answer: Some(answer),
                    },
                })
            },
        )
    }

    /// Scores every step of every candidate given by the client inside `precondition`, and
    /// judges each against the precondition and `goal` (see [`given`](mod@super::given)).
    /// The candidates are assumed validated against the domain.
    pub fn judge(
        &self,
        goal: &[f64],
        candidates: Vec<Path>,
        precondition: Precondition,
    ) -> Result<Vec<Verdict>, PlanningError> {
        given::judge(
            self.domain,
            self.model,
            self.settings.acquisition(),
            goal,
            candidates,
            precondition,
        )
    }
}

/// What one rung of a β relaxation gave ([`relax`]).
enum Rung<T> {
    /// Something to take: the relaxation stops at this rung.
    Taken(T),
    /// Nothing to take, found out in `extensions` RRT extensions; `answer` (if any) is
    /// answered should no later rung take one.
    Passed {
        extensions: usize,
        answer: Option<T>,
    },
}

/// The β relaxation, written once for the planner's proposals and a client's candidates:
/// `rung` tries each precondition of `ladder` in turn until one is [`Rung::Taken`]. The
/// extensions spent on the rungs passed are `credit`ed to what is answered, or added to the
/// [`PlanningError::Stopped`] that ends the search; when no rung takes, the last rung's
/// `answer`, else [`PlanningError::NoPlan`] with every rung's extensions. Any other error
/// ends the search at once.
/// The models' indexes, cheapest first (equal costs in the given order); an error naming
/// `models` when there is none or a cost is not a positive number.
fn cost_order(models: &[PlanModel<'_>]) -> Result<Vec<usize>, PlanningError> {
    if models.is_empty() {
        return Err(PlanningError::settings("models", "no model to plan with"));
    }
    if let Some(m) = models
        .iter()
        .find(|m| !(m.cost.is_finite() && m.cost > 0.0))
    {
        return Err(PlanningError::settings(
            "models",
            format!("a model's cost must be a positive number, not {}", m.cost),
        ));
    }
    let mut order: Vec<usize> = (0..models.len()).collect();
    order.sort_by(|&a, &b| models[a].cost.total_cmp(&models[b].cost));
    Ok(order)
}

fn relax<T>(
    ladder: &[Precondition],
    credit: impl Fn(&mut T, usize),
    mut rung: impl FnMut(Precondition) -> Result<Rung<T>, PlanningError>,
) -> Result<T, PlanningError> {
    let mut spent = 0;
    let mut last = None;
    for &precondition in ladder {
        match rung(precondition) {
            Ok(Rung::Taken(mut taken)) => {
                credit(&mut taken, spent);
                return Ok(taken);
            }
            Ok(Rung::Passed { extensions, answer }) => {
                spent += extensions;
                last = answer.or(last);
            }
            Err(PlanningError::Stopped { reason, extensions }) => {
                return Err(PlanningError::Stopped {
                    reason,
                    extensions: spent + extensions,
                });
            }
            Err(e) => return Err(e),
        }
    }
    match last {
        Some(mut answer) => {
            credit(&mut answer, spent);
            Ok(answer)
        }
        None => Err(PlanningError::NoPlan { extensions: spent }),
    }
}

/// A client's candidates judged and valued inside a precondition ([`Planner::judge_relaxing`]).
#[derive(Debug, Clone)]
pub struct GivenChoice {
    /// Each candidate's verdict, in the order posted.
    pub verdicts: Vec<Verdict>,
    /// The rule whose `α` the eligible ones were compared by.
    pub valued_by: AcquisitionKind,
    /// The precondition they were judged inside.
    pub precondition: Precondition,
    /// The candidate the strategy chose (`None`: none it may take).
    pub chosen: Option<usize>,
}
