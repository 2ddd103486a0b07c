//! Model selection at every fit: how deviations become the MDE's training labels (capped at a
//! multiple of `d_max`, [`capped_labels`]), the kernel ([`best_kernel`]) and the test β a
//! version certifies ([`BetaChoice`]), each chosen by how the fitted model judges its own
//! training transitions held out ([`fit_choosing_label_cap`], [`HeldOutTrust`]); and what the
//! choice costs before it starts ([`selection_cost`]).

use super::estimator::{EstimatorKind, EstimatorParams, Regressor, fit};
use super::margin::{Calibration, LocalMargin};
use crate::gp::{Fold, GpError, Kernel, WarmStart};
use crate::planning::Precondition;
use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// The labels the MDE is fitted on for a label cap (units of `d_max`; 0 = the raw deviations).
pub fn capped_labels(deviations: &[f64], label_cap: f64, d_max: f64) -> Vec<f64> {
    if label_cap > 0.0 {
        deviations
            .iter()
            .map(|d| d.min(label_cap * d_max))
            .collect()
    } else {
        deviations.to_vec()
    }
}

/// How a model fitted with one label cap judges its own training transitions when each
/// state-action is left out in turn, with all its copies: the held-out precondition
/// `μ₋ᵢ + β σ₋ᵢ < d_max` against the truth `deviation_i < d_max`, and the log probability it
/// gives to the truth.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
pub struct HeldOutTrust {
    /// The label cap the model was fitted with (units of `d_max`; 0 = raw labels).
    pub label_cap: f64,
    /// Training transitions whose deviation is below `d_max`.
    pub safe: usize,
    /// Training transitions whose deviation is `d_max` or more.
    pub unsafe_transitions: usize,
    /// Safe transitions inside the held-out precondition.
    pub trusted_safe: usize,
    /// Unsafe transitions inside the held-out precondition (false trust).
    pub trusted_unsafe: usize,
    /// Mean log probability the held-out predictions give to the side of `d_max` each
    /// transition's deviation fell on (`log Φ(±(d_max − μ₋ᵢ)/σ₋ᵢ)`; 0 is perfect), averaged
    /// within each group of identical state-actions and then over the groups.
    pub log_score: f64,
    /// Distinct state-actions (identical feature vectors) among the training transitions:
    /// each is held out with all its copies, so every one is judged as an unseen input
    /// (0 for judgements made before groups were used, which left one transition out).
    pub held_out_groups: usize,
}

impl HeldOutTrust {
    /// The judgement of `gp`'s training points, fitted on `labels` (the `deviations` capped at
    /// `label_cap`), when each group of `groups` (see [`identical_rows`]) is left out in turn,
    /// with each group's held-out log probability of its side of `d_max` (the mean over its
    /// transitions), judged by `precondition`; `None` when the model kept no inverse factor
    /// or a group is invalid.
    pub fn of(
        gp: &dyn Regressor,
        label_cap: f64,
        labels: &[f64],
        deviations: &[f64],
        groups: &[Vec<usize>],
        precondition: Precondition,
    ) -> Option<(Self, Vec<f64>)> {
        let held_out = gp.leave_groups_out(groups)?;
        let d_max = precondition.d_max();
        let mut log_p = Vec::with_capacity(held_out.len());
        let mut t = Self {
            label_cap,
            safe: 0,
            unsafe_transitions: 0,
            trusted_safe: 0,
            trusted_unsafe: 0,
            log_score: 0.0,
            held_out_groups: groups.len(),
        };
        for ((&(residual, sd), &label), &deviation) in held_out.iter().zip(labels).zip(deviations) {
            let mu = label - residual;
            let inside = precondition.inside(mu, sd);
            let z = (d_max - mu) / sd;
            let p_correct = if deviation < d_max {
                normal_tail(-z)
            } else {
                normal_tail(z)
            };
            log_p.push(p_correct.max(1e-300).ln());
            if deviation < d_max {
                t.safe += 1;
                t.trusted_safe += usize::from(inside);
            } else {
                t.unsafe_transitions += 1;
                t.trusted_unsafe += usize::from(inside);
            }
        }
        let per_group: Vec<f64> = groups
            .iter()
            .map(|g| g.iter().map(|&i| log_p[i]).sum::<f64>() / g.len().max(1) as f64)
            .collect();
        t.log_score = per_group.iter().sum::<f64>() / per_group.len().max(1) as f64;
        Some((t, per_group))
    }
}

/// The test β the data certify: the smallest β on a grid of `0, 0.1, …, max_beta` at which the
/// model, judging its own training state-actions held out in groups — by [`fit_choosing_label_cap`],
/// each executed trajectory whole with every copy of its state-actions ([`trajectory_folds`]) — trusts
/// (`μ₋ᵢ + β σ₋ᵢ < d_max`) few enough of the unsafe ones — the rule-of-succession estimate of
/// the false-trust rate, `(trusted unsafe + 1) / (unsafe + 2)`, at most
/// [`CALIBRATED_FALSE_TRUST`] — or `max_beta` when no smaller β is certified. The estimate's
/// `+ 1` keeps β at `max_beta` until enough unsafe transitions were seen to certify anything
/// (49 for a 2 % rate). The rate is estimated where the learner executed; on moves far from
/// every executed trajectory it can be higher (measured in docs/research/continuous-worlds.md).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
pub struct BetaChoice {
    /// The certified β (at most the experiment's `learning.test_beta`).
    pub beta: f64,
    /// Training transitions whose deviation is below `d_max`.
    pub safe: usize,
    /// Training transitions whose deviation is `d_max` or more.
    pub unsafe_transitions: usize,
    /// Safe transitions trusted at `beta`, held out.
    pub trusted_safe: usize,
    /// Unsafe transitions trusted at `beta`, held out (false trust).
    pub trusted_unsafe: usize,
}

/// The false-trust rate (unsafe transitions trusted, of all unsafe ones) a calibrated test β
/// certifies on the held-out training state-actions ([`BetaChoice`]): 2 %, a true-negative rate
/// of 0.98.
pub const CALIBRATED_FALSE_TRUST: f64 = 0.02;

impl BetaChoice {
    /// The choice for `gp`, fitted on `labels` (the `deviations` capped), each fold of `folds`
    /// left out in turn and its judged rows predicted; β on the grid `0, 0.1, …` up to `max_beta` (inclusive; `max_beta`
    /// itself when it is below 0). `None` when the model has no closed-form leave-out.
    pub fn of(
        gp: &dyn Regressor,
        labels: &[f64],
        deviations: &[f64],
        folds: &[Fold],
        d_max: f64,
        max_beta: f64,
    ) -> Option<Self> {
        Some(Self::from_held_out(
            &gp.leave_folds_out(folds)?,
            labels,
            deviations,
            d_max,
            max_beta,
        ))
    }

    /// [`BetaChoice::of`] from the held-out `(y_i − μ₋ᵢ, σ₋ᵢ)` of every training point.
    pub fn from_held_out(
        held_out: &[(f64, f64)],
        labels: &[f64],
        deviations: &[f64],
        d_max: f64,
        max_beta: f64,
    ) -> Self {
        let judged: Vec<(f64, f64, bool)> = held_out
            .iter()
            .zip(labels)
            .zip(deviations)
            .map(|((&(residual, sd), &label), &deviation)| {
                (label - residual, sd, deviation < d_max)
            })
            .collect();
        let at = |beta: f64| {
            let mut c = Self {
                beta,
                safe: 0,
                unsafe_transitions: 0,
                trusted_safe: 0,
                trusted_unsafe: 0,
            };
            for &(mu, sd, safe) in &judged {
                let trusted = mu + beta * sd < d_max;
                if safe {
                    c.safe += 1;
                    c.trusted_safe += usize::from(trusted);
                } else {
                    c.unsafe_transitions += 1;
                    c.trusted_unsafe += usize::from(trusted);
                }
            }
            c
        };
        let certified = |c: &Self| {
            (c.trusted_unsafe as f64 + 1.0) / (c.unsafe_transitions as f64 + 2.0)
                <= CALIBRATED_FALSE_TRUST
        };
        let steps = (max_beta / BETA_GRID_STEP).floor().max(0.0) as usize;
        (0..steps)
            .map(|k| at(k as f64 * BETA_GRID_STEP))
            .find(certified)
            .unwrap_or_else(|| at(max_beta))
    }
}

/// The spacing of the β grid a calibrated test β is chosen on.
const BETA_GRID_STEP: f64 = 0.1;

/// The rows of `x` grouped by identical values (bit for bit, `−0.0` folded into `0.0`, as the
/// planner's caches key them), each group in row order, the groups in order of first
/// appearance: every copy of one state-action in one group.
pub fn identical_rows(x: &DMatrix<f64>) -> Vec<Vec<usize>> {
    group_rows(x, |v| (v + 0.0).to_bits())
}

/// The rows of `x` grouped by the block of a regular grid of `bins` cells per feature (features
/// in the unit box) they fall in, each group in row order, the groups in order of first
/// appearance. Leaving a block out judges how a model carries what it learned into a region it
/// has not seen, as planning asks of it.
pub fn blocks(x: &DMatrix<f64>, bins: usize) -> Vec<Vec<usize>> {
    let bins = bins.max(1);
    group_rows(x, |v| {
        ((v.clamp(0.0, 1.0) * bins as f64) as usize).min(bins - 1)
    })
}

/// The rows of `x` grouped by the values `cell` maps their features to (rows alike in every
/// feature in one group), each group in row order, the groups in order of first appearance:
/// [`identical_rows`] and [`blocks`].
fn group_rows<K: Eq + std::hash::Hash>(
    x: &DMatrix<f64>,
    cell: impl Fn(f64) -> K,
) -> Vec<Vec<usize>> {
    let mut index = std::collections::HashMap::<Vec<K>, usize>::new();
    let mut groups: Vec<Vec<usize>> = Vec::new();
    for (i, row) in x.row_iter().enumerate() {
        let key = row.iter().map(|&v| cell(v)).collect();
        let g = *index.entry(key).or_insert_with(|| {
            groups.push(Vec::new());
            groups.len() - 1
        });
        groups[g].push(i);
    }
    groups
}

/// Rows in folds of whole executed trajectories: fold `T` leaves out every transition of
/// trajectory `T` and every copy of any of its state-actions ([`identical_rows`]), wherever it
/// was executed, and judges `T`'s own transitions. `trajectories[i]` names row `i`'s trajectory;
/// the folds come in order of their first row. With every row its own trajectory these are the
/// copies of each state-action, left out together.
///
/// Why a certified test β ([`BetaChoice`]) is judged on these folds: a state-action held out
/// alone keeps its trajectory's neighbours (the states just before and after it, the same
/// steering), so it is predicted more easily than a move where nothing was executed, which is
/// what a plan asks of the model. On the arm, copies alone certified β 0.2 where the uniform
/// held-out false trust then was 12.8 %; whole trajectories certified 1.4 (0.9 %)
/// (`precond bench mde --calibration`, docs/research/continuous-worlds.md). Copies do not join
/// two trajectories into one fold: a gridworld's trajectories revisit the same cells, and
/// joined they fell into a few giant groups whose absence made every unsafe move look
/// untrusted at a small β (β 1.5 certified where the default map's unseen moves then had
/// 5.4 % false trust). Folds overlap, so a robot that executes one state-action in every
/// trajectory puts all its copies in every fold: `None`, found while building (so the folds
/// never hold more than that), when they would cost the leave-out more than a partition of
/// the rows could ([`Fold::max_work`]); the fit then certifies nothing (its test β stays
/// `learning.test_beta`).
pub fn trajectory_folds(x: &DMatrix<f64>, trajectories: &[i64]) -> Option<Vec<Fold>> {
    let n = x.nrows().min(trajectories.len());
    let mut copies_of = vec![0usize; n];
    let copies: Vec<Vec<usize>> = identical_rows(x)
        .into_iter()
        .map(|g| g.into_iter().filter(|&i| i < n).collect())
        .collect();
    for (k, g) in copies.iter().enumerate() {
        for &i in g {
            copies_of[i] = k;
        }
    }
    let mut order = Vec::<i64>::new();
    let mut by_trajectory = std::collections::HashMap::<i64, Vec<usize>>::new();
    for (i, &t) in trajectories.iter().take(n).enumerate() {
        by_trajectory
            .entry(t)
            .or_insert_with(|| {
                order.push(t);
                Vec::new()
            })
            .push(i);
    }
    let mut work = 0usize;
    let mut folds = Vec::with_capacity(order.len());
    for t in order {
        let own = &by_trajectory[&t];
        let mut rows = own.clone();
        let mut seen: std::collections::HashSet<usize> = own.iter().copied().collect();
        for &i in own {
            for &j in &copies[copies_of[i]] {
                if seen.insert(j) {
                    rows.push(j);
                }
            }
        }
        work = work.saturating_add(rows.len().saturating_mul(rows.len()));
        if work > Fold::max_work(n) {
            return None;
        }
        folds.push(Fold {
            rows,
            judged: own.len(),
        });
    }
    Some(folds)
}

/// Training transitions as the estimator is fitted on them: their features (one row each),
/// deviations, and the executed trajectory each belongs to (which rows a certified test β
/// leaves out together, [`trajectory_folds`]).
#[derive(Debug, Clone, Copy)]
pub struct Training<'a> {
    /// Features, one row per transition.
    pub x: &'a DMatrix<f64>,
    /// Deviation labels, one per row.
    pub deviations: &'a [f64],
    /// The trajectory of each row (any identifiers; equal for rows of one trajectory).
    pub trajectories: &'a [i64],
}

impl Training<'_> {
    /// The rows `rows` of this set, owned.
    fn select(&self, rows: &[usize]) -> (DMatrix<f64>, Vec<f64>, Vec<i64>) {
        (
            self.x.select_rows(rows),
            rows.iter().map(|&i| self.deviations[i]).collect(),
            rows.iter()
                .map(|&i| self.trajectories.get(i).copied().unwrap_or(i as i64))
                .collect(),
        )
    }
}

/// A model fitted with the kernel and the label cap chosen from the data, and how every
/// candidate did.
#[derive(Debug)]
pub struct CapChoice {
    /// The model fitted with the chosen kernel and cap.
    pub gp: Box<dyn Regressor>,
    /// The chosen cap (units of `d_max`; 0 = raw labels).
    pub label_cap: f64,
    /// Every candidate cap's held-out judgement, in the order tried.
    pub trials: Vec<HeldOutTrust>,
    /// Every candidate kernel's fit (empty when one kernel was given).
    pub kernel_trials: Vec<KernelTrial>,
    /// The test β the chosen model certifies, each executed trajectory left out whole
    /// ([`trajectory_folds`]; `None` when it could not be computed).
    pub beta_choice: Option<BetaChoice>,
    /// The locally calibrated margin of the same held-out judgements ([`LocalMargin`];
    /// `None` when they could not be computed).
    pub local_margin: Option<LocalMargin>,
    /// What the fit spent its time on, in order.
    pub phases: Vec<FitPhase>,
}

/// The test β `gp` certifies ([`BetaChoice`]) and its locally calibrated margin
/// ([`LocalMargin`]), both from one leave-out of each executed trajectory whole
/// ([`trajectory_folds`]), `gp` fitted on `labels` (the training deviations capped), for β up
/// to `max_beta`. `None` for both where the folds or the leave-out cannot be computed.
pub fn held_out_margins(
    gp: &dyn Regressor,
    training: Training<'_>,
    labels: &[f64],
    d_max: f64,
    max_beta: f64,
) -> (Option<BetaChoice>, Option<LocalMargin>) {
    let Some(held_out) = trajectory_folds(training.x, training.trajectories)
        .and_then(|folds| gp.leave_folds_out(&folds))
    else {
        return (None, None);
    };
    let choice = BetaChoice::from_held_out(&held_out, labels, training.deviations, d_max, max_beta);
    let x = training.x;
    // Row-major: the column-major storage of the transpose.
    let rows = x.transpose();
    let margin = LocalMargin::from_held_out(
        rows.as_slice(),
        x.ncols(),
        &held_out,
        labels,
        training.deviations,
        Calibration {
            d_max,
            max_beta,
            false_trust: CALIBRATED_FALSE_TRUST,
        },
    );
    (Some(choice), margin)
}

/// One phase of a fit and its wall time.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
pub struct FitPhase {
    /// What it did, e.g. `kernels: 3 fits`, `label caps: 2 more fits`, `warm fit`,
    /// `certified β`.
    pub phase: String,
    /// Seconds it took.
    pub seconds: f64,
}

/// Times `phase`, adding it to `phases`.
fn timed<T>(phases: &mut Vec<FitPhase>, phase: impl Into<String>, f: impl FnOnce() -> T) -> T {
    let started = Instant::now();
    let out = f();
    phases.push(FitPhase {
        phase: phase.into(),
        seconds: started.elapsed().as_secs_f64(),
    });
    out
}

/// How a version's kernel and label cap were chosen, and what its fit spent its time on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
pub struct SelectionRecord {
    /// The version whose fit chose the kernel and the label cap this one answers with (itself
    /// when it chose them).
    pub selected_at_version: i64,
    /// Training transitions of that fit.
    pub selected_n_train: usize,
    /// Why this fit chose anew, or kept the choice (a sentence).
    pub reason: String,
    /// What this fit spent its time on, in order.
    pub phases: Vec<FitPhase>,
}

/// A warm refit whose log marginal likelihood per training transition fell by more than this
/// many nats from the version before it is fitted again with a new model selection: the new
/// data no longer fit the kept kernel and cap (a typical batch moves it by hundredths).
pub const LIKELIHOOD_DROP: f64 = 0.2;

/// How the next fit is made ([`refit_plan`]).
#[derive(Debug, Clone, PartialEq)]
pub enum RefitPlan {
    /// Model selection over every candidate kernel and cap ([`fit_choosing_label_cap`]).
    Select {
        /// Why.
        reason: String,
    },
    /// One fit from the previous optimum with its kernel and cap ([`refit_warm`]).
    Warm {
        /// What it keeps.
        carry: Carry,
        /// The version whose fit made the choice it keeps.
        selected_at_version: i64,
        /// That fit's training transitions.
        selected_n_train: usize,
        /// The previous version's log marginal likelihood per training transition, against
        /// which the warm fit's is compared ([`LIKELIHOOD_DROP`]).
        previous_lml_per_transition: f64,
        /// Why it keeps the choice.
        reason: String,
    },
}

/// What the previous version tells the next fit.
#[derive(Debug, Clone, Copy)]
pub struct Previous<'a> {
    /// Its version (0: the prior).
    pub version: i64,
    /// Its regressor, kernel, cap and optimum (`None` for the prior).
    pub fitted: Option<(&'a dyn Regressor, f64)>,
    /// Its selection record (`None` for versions fitted before records were kept).
    pub selection: Option<&'a SelectionRecord>,
}

/// Whether the fit of version `version` on `n` transitions with regressor `kind` chooses the
/// kernel and label cap anew or keeps `previous`'s (every `every`-th fit chooses; so does the
/// first, one after the data doubled since the last choice, one with another regressor, and
/// one whose candidates no longer include the kept kernel or cap).
pub fn refit_plan(
    previous: Previous<'_>,
    version: i64,
    n: usize,
    kind: EstimatorKind,
    kernels: &[Kernel],
    caps: &[f64],
    every: usize,
) -> RefitPlan {
    let select = |reason: String| RefitPlan::Select { reason };
    let Some((gp, label_cap)) = previous.fitted else {
        return select("the first fit chooses the kernel and the label cap".into());
    };
    if every <= 1 {
        return select("mde.reselect_every is 1: every fit chooses".into());
    }
    let Some(record) = previous.selection else {
        return select(format!(
            "version {} recorded no selection to keep",
            previous.version
        ));
    };
    let since = version - record.selected_at_version;
    if since >= every as i64 {
        return select(format!(
            "every {every}th fit chooses anew (the last choice was version {})",
            record.selected_at_version
        ));
    }
    if n >= 2 * record.selected_n_train.max(1) {
        return select(format!(
            "the data doubled since the last choice ({} → {n} transitions)",
            record.selected_n_train
        ));
    }
    if gp.kind() != kind {
        return select(format!(
            "the regressor changed ({} → {})",
            gp.kind().as_str(),
            kind.as_str()
        ));
    }
    let Some(h) = gp.hyperparameters() else {
        return select(format!(
            "the {} estimator keeps no single optimum to start from",
            gp.kind().as_str()
        ));
    };
    if !kernels.contains(&h.kernel) || !caps.contains(&label_cap) {
        return select("the kept kernel or label cap is no longer a candidate".into());
    }
    let noise = gp.noise_summary().map(|s| s.noise_model);
    RefitPlan::Warm {
        carry: Carry {
            kernel: h.kernel,
            label_cap,
            warm: WarmStart::of(h, noise.as_ref()),
        },
        selected_at_version: record.selected_at_version,
        selected_n_train: record.selected_n_train,
        previous_lml_per_transition: gp.log_marginal_likelihood() / gp.n_train().max(1) as f64,
        reason: format!(
            "keeps version {}'s choice (fit {since} of every {every}), from version {}'s optimum",
            record.selected_at_version, previous.version
        ),
    }
}

/// What a refit takes from the version before it: the kernel and label cap that version's
/// model selection chose, and its optimum to start from ([`refit_warm`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Carry {
    /// The kernel kept.
    pub kernel: Kernel,
    /// The label cap kept (units of `d_max`; 0 = raw labels).
    pub label_cap: f64,
    /// The previous optimum.
    pub warm: WarmStart,
}

/// A refit after more data that keeps the previous version's kernel and label cap and starts
/// the hyperparameter optimisation from its optimum (no restarts, no screening): one fit where
/// [`fit_choosing_label_cap`] makes one per candidate kernel and cap, each from several starts.
/// The kept cap's held-out judgement and the certified test β are computed as after a
/// selection. The caller decides when the data call for a new selection instead.
pub fn refit_warm(
    training: Training<'_>,
    precondition: Precondition,
    carry: &Carry,
    kind: EstimatorKind,
    params: &EstimatorParams,
) -> Result<CapChoice, GpError> {
    let (x, deviations) = (training.x, training.deviations);
    let d_max = precondition.d_max();
    let params = params
        .with_kernel(carry.kernel)?
        .with_warm(Some(carry.warm.clone()))?;
    let labels = capped_labels(deviations, carry.label_cap, d_max);
    let mut phases = Vec::new();
    let gp = timed(&mut phases, "warm fit", || {
        fit(kind, x, &DVector::from_column_slice(&labels), &params)
    })?;
    let (trials, (beta_choice, local_margin)) = if kind.judges_held_out() {
        timed(&mut phases, "held-out judgements, certified β", || {
            let groups = identical_rows(x);
            let trial = HeldOutTrust::of(
                gp.as_ref(),
                carry.label_cap,
                &labels,
                deviations,
                &groups,
                precondition,
            )
            .map(|(t, _)| t);
            let margins =
                held_out_margins(gp.as_ref(), training, &labels, d_max, precondition.beta());
            (trial.into_iter().collect(), margins)
        })
    } else {
        (Vec::new(), (None, None))
    };
    Ok(CapChoice {
        gp,
        label_cap: carry.label_cap,
        trials,
        kernel_trials: Vec::new(),
        beta_choice,
        local_margin,
        phases,
    })
}

/// How one candidate kernel's fit did on the first candidate cap's labels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
pub struct KernelTrial {
    /// The kernel.
    pub kernel: Kernel,
    /// Its fit's log marginal likelihood (the largest is kept unless another kernel is clearly
    /// better held out, see [`best_kernel`]).
    pub log_marginal_likelihood: f64,
    /// Its judgement of the training state-actions, each left out with its copies
    /// ([`HeldOutTrust::log_score`]: the mean log probability of the side of `d_max` it fell
    /// on). `None` when it could not be computed, and for trials stored before it existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held_out_log_score: Option<f64>,
}

/// What [`fit_choosing_label_cap`] costs on `n` rows of dimension `d`: an exact fit per kernel
/// (on the first cap's labels) and per further label cap, on all of them (exact), or that
/// choice on at most [`EstimatorParams::selection_subset`] rows and one sparse fit on all of
/// them (sparse).
pub fn selection_cost(
    kind: EstimatorKind,
    n: usize,
    d: usize,
    kernels: usize,
    caps: usize,
    params: &EstimatorParams,
) -> crate::gp::FitCost {
    let choices = kernels.max(1) + caps.max(1) - 1;
    // The kernels' fits run at once, then the further caps' ([`concurrently`]).
    let at_once = selection_threads(kernels.max(caps.max(1) - 1));
    if kind.judges_held_out() {
        params.cost(kind, n, d).times(choices).alongside(at_once)
    } else if choices > 1 {
        params
            .cost(EstimatorKind::Exact, n.min(params.selection_subset()), d)
            .times(choices)
            .alongside(at_once)
            .then(params.cost(kind, n, d))
    } else {
        params.cost(kind, n, d)
    }
}

/// Fits one model per candidate label cap (units of `d_max`; 0 = raw labels) and keeps the one
/// whose held-out predictions best say which side of `d_max` each training state-action's
/// deviation fell on: the highest mean `log Φ(±(d_max − μ₋ᵢ)/σ₋ᵢ)` (a proper scoring rule of
/// exactly what decides the precondition), ties to the larger cap (raw labels count as the
/// largest). A state-action is held out with every copy of it ([`identical_rows`]): a
/// deterministic world's robot executes the same moves again and again, and a copy left in
/// would predict its twin, so leaving out one transition would judge the noise level, not how
/// the model generalises to state-actions it has not seen, which is what planning asks of it.
/// When raw labels are a candidate, a cap replaces them only if its gain is at least
/// [`CAP_GAIN_STANDARD_ERRORS`] standard errors of the per-state-action differences: the
/// paper's labels stay unless the data clearly say otherwise. Groups are left out in closed
/// form, so a candidate costs one fit. With one candidate that one is kept. Errors when a fit
/// fails.
///
/// Before the caps, with several candidate `kernels`, each is fitted on the first candidate
/// cap's labels and [`best_kernel`] keeps one: the highest log marginal likelihood unless
/// another kernel judges the training state-actions clearly better held out (the caps then
/// compete with that kernel).
///
/// The regressor is `kind`. An estimator that judges held out in closed form
/// ([`EstimatorKind::judges_held_out`]: the exact GP, local experts) is fitted per candidate
/// itself. The sparse GP has no closed-form leave-out, so with it the kernel
/// and the cap are chosen the same way by exact GPs on an evenly spaced subset of at most
/// [`EstimatorParams::selection_subset`] transitions, and the sparse GP is then fitted on all
/// of them with
/// them.
pub fn fit_choosing_label_cap(
    training: Training<'_>,
    precondition: Precondition,
    kernels: &[Kernel],
    caps: &[f64],
    kind: EstimatorKind,
    params: &EstimatorParams,
) -> Result<CapChoice, GpError> {
    if !kind.judges_held_out() {
        // The kernel, the cap and the test β are chosen by exact GPs on a subset when there
        // is a choice to make; a fixed kernel and cap fit the sparse GP alone (no β is
        // certified then: the sparse GP has no closed-form leave-out).
        let mut phases = Vec::new();
        let (kernel, label_cap, trials, kernel_trials, beta_choice) =
            if caps.len() > 1 || kernels.len() > 1 {
                let rows = evenly_spaced(training.x.nrows(), params.selection_subset());
                let (x, deviations, trajectories) = training.select(&rows);
                let subset = Training {
                    x: &x,
                    deviations: &deviations,
                    trajectories: &trajectories,
                };
                let c = choose_closed_form(
                    EstimatorKind::Exact,
                    subset,
                    precondition,
                    kernels,
                    caps,
                    params,
                )?;
                phases.extend(c.phases.into_iter().map(|p| FitPhase {
                    phase: format!("on {} transitions: {}", rows.len(), p.phase),
                    ..p
                }));
                (
                    c.gp.hyperparameters()
                        .map_or(params.gp().kernel, |h| h.kernel),
                    c.label_cap,
                    c.trials,
                    c.kernel_trials,
                    c.beta_choice,
                )
            } else {
                (
                    kernels.first().copied().unwrap_or(params.gp().kernel),
                    caps.first().copied().unwrap_or(0.0),
                    Vec::new(),
                    Vec::new(),
                    None,
                )
            };
        let labels = capped_labels(training.deviations, label_cap, precondition.d_max());
        let params = params.with_kernel(kernel)?;
        let gp = timed(&mut phases, "sparse fit", || {
            fit(kind, training.x, &DVector::from_vec(labels), &params)
        })?;
        return Ok(CapChoice {
            gp,
            label_cap,
            trials,
            kernel_trials,
            beta_choice,
            local_margin: None,
            phases,
        });
    }
    choose_closed_form(kind, training, precondition, kernels, caps, params)
}

/// The kernel to keep among `trials`, given each trial's held-out log probabilities per
/// state-action group (`held_out[i]`, paired across trials; `None` when not computed): the one
/// with the highest log marginal likelihood (the evidence of each kernel on the same labels),
/// unless another is [clearly better](CAP_GAIN_STANDARD_ERRORS) held out — then, of those, the
/// one with the highest held-out score. `None` for no trials.
///
/// Why both: the likelihood kept Matérn 5/2 over 1/2 on a gridworld whose deviation jumps
/// (held-out TPR 0.86 against 0.94), and the held-out score alone, in the learning loop, won
/// the gridworlds +0.065 ± 0.025 success but flipped between 3/2 and 5/2 on the pusher, where
/// their scores differ by far less than their noise, and a seeded pusher test plan then crossed
/// `d_max` (docs/research/continuous-worlds.md). A kernel leaves the likelihood's choice only
/// when the data clearly say so, as a label cap replaces raw labels.
pub fn best_kernel(trials: &[KernelTrial], held_out: &[Option<Vec<f64>>]) -> Option<usize> {
    let by_evidence = (0..trials.len()).reduce(|best, i| {
        if trials[i].log_marginal_likelihood > trials[best].log_marginal_likelihood {
            i
        } else {
            best
        }
    })?;
    let Some(Some(base)) = held_out.get(by_evidence) else {
        return Some(by_evidence);
    };
    let score = |i: usize| trials[i].held_out_log_score.unwrap_or(f64::NEG_INFINITY);
    let challenger = (0..trials.len())
        .filter(|&i| i != by_evidence)
        .filter(|&i| {
            held_out
                .get(i)
                .and_then(Option::as_ref)
                .is_some_and(|lp| lp.len() == base.len() && clearly_better(lp, base))
        })
        .reduce(|best, i| if score(i) > score(best) { i } else { best });
    Some(challenger.unwrap_or(by_evidence))
}

/// How many of `choices` independent fits of a model selection run at once: one per core, at
/// most one per choice ([`concurrently`]). Their peak memory adds up
/// ([`selection_cost`](crate::gp::FitCost::alongside)).
pub fn selection_threads(choices: usize) -> usize {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    choices.clamp(1, cores.max(1))
}

/// `f` of every item, in order, run on up to [`selection_threads`] scoped threads: the fits of
/// a model selection's candidates are independent and each is seeded, so the answers are the
/// ones a loop would give, sooner (an exact fit of up to ~1,200 rows runs its linear algebra on
/// one core). The threads inherit the caller's scheduling priority (the service fits at nice
/// +10). A panic in `f` is re-raised here.
fn concurrently<T: Sync, R: Send>(items: &[T], f: impl Fn(&T) -> R + Sync) -> Vec<R> {
    let threads = selection_threads(items.len());
    if threads <= 1 {
        return items.iter().map(f).collect();
    }
    let next = std::sync::atomic::AtomicUsize::new(0);
    let mut done: Vec<(usize, R)> = std::thread::scope(|scope| {
        let workers: Vec<_> = (0..threads)
            .map(|_| {
                scope.spawn(|| {
                    let mut mine = Vec::new();
                    loop {
                        let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        let Some(item) = items.get(i) else {
                            return mine;
                        };
                        mine.push((i, f(item)));
                    }
                })
            })
            .collect();
        workers
            .into_iter()
            .flat_map(|w| w.join().unwrap_or_else(|e| std::panic::resume_unwind(e)))
            .collect()
    });
    done.sort_by_key(|(i, _)| *i);
    done.into_iter().map(|(_, r)| r).collect()
}

/// `k` indices evenly spaced over `0..n` (all of them when `n ≤ k`).
fn evenly_spaced(n: usize, k: usize) -> Vec<usize> {
    if n <= k {
        return (0..n).collect();
    }
    (0..k).map(|i| i * n / k).collect()
}

/// [`fit_choosing_label_cap`] with an estimator `kind` that judges held out in closed form.
fn choose_closed_form(
    kind: EstimatorKind,
    training: Training<'_>,
    precondition: Precondition,
    kernels: &[Kernel],
    caps: &[f64],
    params: &EstimatorParams,
) -> Result<CapChoice, GpError> {
    let (x, deviations) = (training.x, training.deviations);
    let d_max = precondition.d_max();
    let first_cap = caps.first().copied().unwrap_or(0.0);
    let mut kernel_trials = Vec::new();
    let mut first_fit = None;
    let groups = identical_rows(x);
    let mut phases = Vec::new();
    let started = Instant::now();
    let params = if kernels.len() > 1 {
        let capped = capped_labels(deviations, first_cap, d_max);
        let labels = DVector::from_column_slice(&capped);
        let mut fits: Vec<(Box<dyn Regressor>, EstimatorParams)> = Vec::new();
        let mut held_out = Vec::new();
        let tried = concurrently(kernels, |&kernel| {
            let p = params.with_kernel(kernel)?;
            let gp = fit(kind, x, &labels, &p)?;
            let judged = HeldOutTrust::of(
                gp.as_ref(),
                first_cap,
                &capped,
                deviations,
                &groups,
                precondition,
            )
            .filter(|(t, _)| t.log_score.is_finite());
            Ok::<_, GpError>((gp, p, judged))
        });
        for (&kernel, tried) in kernels.iter().zip(tried) {
            let (gp, p, judged) = tried?;
            kernel_trials.push(KernelTrial {
                kernel,
                log_marginal_likelihood: gp.log_marginal_likelihood(),
                held_out_log_score: judged.as_ref().map(|(t, _)| t.log_score),
            });
            held_out.push(judged.map(|(_, lp)| lp));
            fits.push((gp, p));
        }
        let best = best_kernel(&kernel_trials, &held_out);
        let best = best.ok_or_else(|| GpError::InvalidState("no kernel to fit".into()))?;
        let (gp, p) = fits.swap_remove(best);
        first_fit = Some(gp);
        phases.push(FitPhase {
            phase: format!("kernels: {} fits", kernels.len()),
            seconds: started.elapsed().as_secs_f64(),
        });
        p
    } else {
        match kernels.first() {
            Some(&k) => params.with_kernel(k)?,
            None => params.clone(),
        }
    };
    let mut fitted = Vec::with_capacity(caps.len());
    let started = Instant::now();
    // The first cap's model is the kernel choice's fit when there was one; the other caps are
    // fitted (and judged) concurrently.
    let reuse_first = first_fit.is_some();
    let cap_fits = caps.len() - usize::from(reuse_first && !caps.is_empty());
    let indices: Vec<usize> = (0..caps.len()).collect();
    let tried = concurrently(&indices, |&i| {
        let labels = capped_labels(deviations, caps[i], d_max);
        let gp = if reuse_first && i == 0 {
            None
        } else {
            Some(fit(kind, x, &DVector::from_column_slice(&labels), &params)?)
        };
        let judged = gp.as_ref().map(|gp| {
            HeldOutTrust::of(
                gp.as_ref(),
                caps[i],
                &labels,
                deviations,
                &groups,
                precondition,
            )
        });
        Ok::<_, GpError>((labels, gp, judged))
    });
    for (&cap, tried) in caps.iter().zip(tried) {
        let (gp, judged) = match tried? {
            (_, Some(gp), Some(judged)) => (gp, judged),
            (labels, _, _) => {
                let gp = first_fit
                    .take()
                    .ok_or_else(|| GpError::InvalidState("no first fit to reuse".into()))?;
                let judged =
                    HeldOutTrust::of(gp.as_ref(), cap, &labels, deviations, &groups, precondition);
                (gp, judged)
            }
        };
        fitted.push((cap, gp, judged));
    }
    let size = |cap: f64| if cap > 0.0 { cap } else { f64::INFINITY };
    let score = |j: &Option<(HeldOutTrust, Vec<f64>)>| {
        j.as_ref().map_or(f64::NEG_INFINITY, |(t, _)| t.log_score)
    };
    let mut best = (0..fitted.len())
        .max_by(|&a, &b| {
            let ((ca, _, ja), (cb, _, jb)) = (&fitted[a], &fitted[b]);
            score(ja)
                .total_cmp(&score(jb))
                .then(size(*ca).total_cmp(&size(*cb)))
        })
        .ok_or_else(|| GpError::InvalidState("no label cap to fit with".into()))?;
    if let Some(raw) = fitted.iter().position(|(cap, ..)| *cap == 0.0)
        && let (Some((_, lp_best)), Some((_, lp_raw))) = (&fitted[best].2, &fitted[raw].2)
        && !clearly_better(lp_best, lp_raw)
    {
        best = raw;
    }
    let trials = fitted
        .iter()
        .filter_map(|(_, _, j)| j.as_ref().map(|(t, _)| *t))
        .collect();
    let (label_cap, gp, _) = fitted.swap_remove(best);
    phases.push(FitPhase {
        phase: if cap_fits > 0 {
            format!("label caps: {} candidates, {cap_fits} fits", caps.len())
        } else {
            "fit".to_string()
        },
        seconds: started.elapsed().as_secs_f64(),
    });
    // The test β the chosen model certifies, and its local margin, each trajectory left out
    // whole.
    let (beta_choice, local_margin) = timed(&mut phases, "certified β", || {
        held_out_margins(
            gp.as_ref(),
            training,
            &capped_labels(deviations, label_cap, d_max),
            d_max,
            precondition.beta(),
        )
    });
    Ok(CapChoice {
        gp,
        label_cap,
        trials,
        kernel_trials,
        beta_choice,
        local_margin,
        phases,
    })
}

/// How many standard errors of the paired per-state-action differences in held-out log
/// probability a label cap must gain over raw labels to replace them.
pub const CAP_GAIN_STANDARD_ERRORS: f64 = 2.0;

/// Whether log probabilities `a` beat `b` (paired, same transitions) by at least
/// [`CAP_GAIN_STANDARD_ERRORS`] standard errors of their mean difference.
fn clearly_better(a: &[f64], b: &[f64]) -> bool {
    let n = a.len().min(b.len());
    if n < 2 {
        return false;
    }
    let d: Vec<f64> = a.iter().zip(b).map(|(x, y)| x - y).collect();
    let mean = d.iter().sum::<f64>() / n as f64;
    let var = d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    mean > 0.0 && mean >= CAP_GAIN_STANDARD_ERRORS * (var / n as f64).sqrt()
}

/// `Φ(−β)`, the standard normal's upper tail beyond `β`.
pub fn normal_tail(beta: f64) -> f64 {
    0.5 * libm::erfc(beta / std::f64::consts::SQRT_2)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gp::{GpModel, Kernel, NoiseMode};
    use crate::mde::gp_params;

    const D_MAX: f64 = 0.1;

    /// The precondition at β = 2 and `D_MAX`.
    fn at_beta_2() -> Precondition {
        Precondition::new(2.0, D_MAX).unwrap()
    }

    fn gp() -> crate::gp::ValidGpParams {
        gp_params(NoiseMode::Homoscedastic, Kernel::Matern52, 0.0, 0, 7)
            .check()
            .expect("valid")
    }

    fn params() -> EstimatorParams {
        EstimatorParams::new(gp().params().clone(), 64).expect("valid")
    }

    /// Points on a 2-D lattice with the deviation a function of the point.
    fn world(f: impl Fn(f64, f64) -> f64) -> (DMatrix<f64>, Vec<f64>) {
        let pts: Vec<(f64, f64)> = (0..12)
            .flat_map(|i| (0..5).map(move |j| (i as f64 / 11.0, j as f64 / 4.0)))
            .collect();
        let x = DMatrix::from_fn(
            pts.len(),
            2,
            |r, c| if c == 0 { pts[r].0 } else { pts[r].1 },
        );
        let d = pts.iter().map(|&(a, b)| f(a, b)).collect();
        (x, d)
    }

    /// `n × 5` lattice points over the unit square with the deviation a function of the point.
    fn dense_world(n: usize, f: impl Fn(f64, f64) -> f64) -> (DMatrix<f64>, Vec<f64>) {
        let pts: Vec<(f64, f64)> = (0..n)
            .flat_map(|i| (0..5).map(move |j| (i as f64 / (n - 1) as f64, j as f64 / 4.0)))
            .collect();
        let x = DMatrix::from_fn(
            pts.len(),
            2,
            |r, c| if c == 0 { pts[r].0 } else { pts[r].1 },
        );
        (x, pts.iter().map(|&(a, b)| f(a, b)).collect())
    }

    /// The β `gp` (fitted on raw `deviations`) certifies at most 2 with each state-action held
    /// out with its copies alone.
    fn certified_on_copies(gp: &dyn Regressor, x: &DMatrix<f64>, deviations: &[f64]) -> BetaChoice {
        BetaChoice::of(
            gp,
            deviations,
            deviations,
            &Fold::whole(&identical_rows(x)),
            D_MAX,
            2.0,
        )
        .expect("closed form")
    }

    /// Every row its own trajectory.
    fn own_trajectories(x: &DMatrix<f64>) -> Vec<i64> {
        (0..x.nrows() as i64).collect()
    }

    /// The exact GP of [`params`] fitted on raw `deviations`.
    fn exact_fit(x: &DMatrix<f64>, deviations: &[f64]) -> Box<dyn Regressor> {
        fit(
            EstimatorKind::Exact,
            x,
            &DVector::from_column_slice(deviations),
            &params(),
        )
        .expect("fits")
    }

    #[test]
    fn the_certified_beta_is_the_smallest_that_keeps_held_out_false_trust_within_the_rate() {
        // A deviation that ramps through d_max: a small β trusts the unsafe side's edge.
        let ramp = |a: f64, _: f64| (a - 0.3).max(0.0) * 0.5;
        let (x, deviations) = dense_world(40, ramp);
        let gp = exact_fit(&x, &deviations);
        let groups = Fold::whole(&identical_rows(&x));
        let c = BetaChoice::of(gp.as_ref(), &deviations, &deviations, &groups, D_MAX, 2.0)
            .expect("closed form");
        let rate =
            |c: &BetaChoice| (c.trusted_unsafe as f64 + 1.0) / (c.unsafe_transitions as f64 + 2.0);
        assert_eq!(c.safe + c.unsafe_transitions, deviations.len());
        assert!(c.unsafe_transitions >= 49, "{c:?}");
        assert!(c.beta >= 0.0 && c.beta <= 2.0, "{c:?}");
        if c.beta < 2.0 {
            assert!(rate(&c) <= CALIBRATED_FALSE_TRUST, "{c:?}");
        }
        // Minimal: one grid step below, the rate is above the bound.
        if c.beta >= BETA_GRID_STEP {
            let below = BetaChoice::of(
                gp.as_ref(),
                &deviations,
                &deviations,
                &groups,
                D_MAX,
                c.beta - BETA_GRID_STEP + 1e-9,
            )
            .unwrap();
            assert!(
                below.beta < c.beta && rate(&below) > CALIBRATED_FALSE_TRUST,
                "{c:?} {below:?}"
            );
        }
        // A smooth ramp densely sampled is predicted well held out: some β below 2 is
        // certified, and safe transitions are trusted at it.
        assert!(c.beta < 2.0 && c.trusted_safe > 0, "{c:?}");
    }

    #[test]
    fn trajectories_and_copies_are_left_out_together() {
        // Rows 0 and 3 are copies, so are 2 and 6; trajectories {0, 1}, {2}, {3}, {4, 5}, {6}.
        let x = DMatrix::from_row_slice(7, 1, &[0.0, 0.1, 0.2, 0.0, 0.4, 0.5, 0.2]);
        let folds = trajectory_folds(&x, &[7, 7, 8, 9, 3, 3, 2]).expect("within budget");
        let fold = |rows: &[usize], judged| Fold {
            rows: rows.to_vec(),
            judged,
        };
        // Each trajectory judged on its own rows, with every copy of them left out too; a copy
        // does not join two trajectories' folds.
        assert_eq!(
            folds,
            vec![
                fold(&[0, 1, 3], 2),
                fold(&[2, 6], 1),
                fold(&[3, 0], 1),
                fold(&[4, 5], 2),
                fold(&[6, 2], 1),
            ]
        );
        // Every row its own trajectory: the copies of each state-action.
        let alone = trajectory_folds(&x, &[0, 1, 2, 3, 4, 5, 6]).expect("within budget");
        assert_eq!(alone[0], fold(&[0, 3], 1));
        assert_eq!(alone[3], fold(&[3, 0], 1));
        assert_eq!(alone[1], fold(&[1], 1));
    }

    /// The label-cap choice with raw labels and Matérn 5/2 only, at β = 2.
    fn fit_raw_matern52(x: &DMatrix<f64>, deviations: &[f64], trajectories: &[i64]) -> CapChoice {
        fit_choosing_label_cap(
            Training {
                x,
                deviations,
                trajectories,
            },
            at_beta_2(),
            &[Kernel::Matern52],
            &[0.0],
            EstimatorKind::Exact,
            &params(),
        )
        .expect("fits")
    }

    #[test]
    fn a_state_action_repeated_in_every_trajectory_certifies_nothing_rather_than_costing_more() {
        // 60 trajectories, each one state-action of its own and one shared by all: every fold
        // would hold all 60 copies of the shared one, 60 · 61² in all where a partition of the
        // 120 rows costs at most 120². The folds are refused while being built; the fit stands
        // and certifies nothing.
        let mut rows = Vec::new();
        let mut deviations = Vec::new();
        let mut trajectories = Vec::new();
        for t in 0..60 {
            rows.extend([t as f64 / 59.0, 0.5, 0.5, 0.5]);
            deviations.extend([if t < 30 { 0.0 } else { 2.0 * D_MAX }, 0.0]);
            trajectories.extend([t, t]);
        }
        let x = DMatrix::from_row_slice(120, 2, &rows);
        assert_eq!(trajectory_folds(&x, &trajectories), None);
        let c = fit_raw_matern52(&x, &deviations, &trajectories);
        assert_eq!(c.beta_choice, None);
    }

    #[test]
    fn a_trajectory_held_out_whole_certifies_a_larger_beta_than_its_points_alone() {
        // Trajectories run along the first feature, densely; the deviation ramps through d_max
        // along the second, across trajectories. A point held out alone is predicted from its
        // trajectory's neighbours; a trajectory held out whole only from the next ones.
        let ramp = |a: f64, b: f64| (b - 0.3).max(0.0) * 0.5 + 0.02 * (6.0 * a).sin();
        let (x, deviations) = dense_world(40, |a, b| ramp(b, a));
        let along: Vec<i64> = (0..x.nrows())
            .map(|r| (x[(r, 1)] * 4.0).round() as i64)
            .collect();
        let c = fit_raw_matern52(&x, &deviations, &along);
        let by_trajectory = c.beta_choice.expect("closed form");
        let alone = certified_on_copies(c.gp.as_ref(), &x, &deviations);
        assert!(
            by_trajectory.beta > alone.beta,
            "{by_trajectory:?} {alone:?}"
        );
    }

    #[test]
    fn too_few_unsafe_transitions_certify_nothing_below_the_bound() {
        // 12 × 5 points, a cliff: at most 30 unsafe transitions, fewer than the 49 a 2 % rate
        // needs even with none trusted.
        let (x, deviations) = world(|a, _| if a < 0.5 { 0.0 } else { 2.0 });
        let gp = exact_fit(&x, &deviations);
        let c = certified_on_copies(gp.as_ref(), &x, &deviations);
        assert!(c.unsafe_transitions < 49, "{c:?}");
        assert_eq!(c.beta, 2.0, "{c:?}");
    }

    #[test]
    fn the_chosen_cap_judges_the_held_out_transitions_best() {
        // A world that jumps (a cliff, labels 0 or 20 d_max) and one that ramps (deviation
        // grows linearly through d_max): the rule must hold on both, whatever it picks.
        let worlds = [
            world(|a, _| if a < 0.5 { 0.0 } else { 2.0 }),
            world(|a, _| (a - 0.3).max(0.0) * 0.8),
        ];
        for (x, deviations) in &worlds {
            let caps = [2.0, 5.0, 0.0];
            let c = fit_choosing_label_cap(
                Training {
                    x,
                    deviations,
                    trajectories: &own_trajectories(x),
                },
                at_beta_2(),
                &[Kernel::Matern52],
                &caps,
                EstimatorKind::Exact,
                &params(),
            )
            .expect("fits");
            assert_eq!(c.trials.len(), 3);
            for t in &c.trials {
                assert_eq!(t.safe + t.unsafe_transitions, deviations.len());
                assert!(t.trusted_safe <= t.safe && t.trusted_unsafe <= t.unsafe_transitions);
                assert!(t.log_score <= 0.0 && t.log_score.is_finite(), "{t:?}");
            }
            // The chosen cap scores best, or it is raw labels kept because no cap beat them
            // clearly.
            let chosen = c
                .trials
                .iter()
                .find(|t| t.label_cap == c.label_cap)
                .unwrap();
            let top = c
                .trials
                .iter()
                .map(|t| t.log_score)
                .fold(f64::MIN, f64::max);
            assert!(
                chosen.log_score == top || c.label_cap == 0.0,
                "{:?}",
                c.trials
            );
            // The model returned is the one fitted with the chosen cap.
            let labels = capped_labels(deviations, c.label_cap, D_MAX);
            let again = GpModel::fit(x, &DVector::from_vec(labels), &gp()).unwrap();
            let q = DMatrix::from_row_slice(1, 2, &[0.42, 0.5]);
            assert_eq!(c.gp.predict(&q).mean, again.predict(&q).mean);
        }
    }

    #[test]
    fn held_out_judgements_match_refitting_without_every_copy_of_the_state_action() {
        let (x0, d0) = world(|a, b| if a < 0.5 && b < 0.6 { 0.0 } else { 0.4 });
        // Some state-actions executed again: three more copies of point 7, one of 30 and 44.
        let rows: Vec<usize> = (0..d0.len()).chain([7, 7, 7, 30, 44]).collect();
        let x = x0.select_rows(&rows);
        let deviations: Vec<f64> = rows.iter().map(|&i| d0[i]).collect();
        let groups = identical_rows(&x);
        assert_eq!(groups.len(), d0.len());
        assert_eq!(groups[7], vec![7, 60, 61, 62]);
        assert_eq!(groups[30], vec![30, 63]);
        let labels = capped_labels(&deviations, 2.0, D_MAX);
        let gp = GpModel::fit(&x, &DVector::from_vec(labels.clone()), &gp()).unwrap();
        let (t, per_group) =
            HeldOutTrust::of(&gp, 2.0, &labels, &deviations, &groups, at_beta_2()).unwrap();
        assert_eq!(t.held_out_groups, groups.len());
        assert_eq!(per_group.len(), groups.len());
        // Refit without each state-action's copies with the same hyperparameters and judge
        // them directly.
        let noise = gp.hyperparameters().noise_variance + gp.jitter();
        let (mut trusted_safe, mut trusted_unsafe, mut log_score) = (0, 0, 0.0);
        for group in &groups {
            let keep: Vec<usize> = (0..rows.len()).filter(|j| !group.contains(j)).collect();
            let xi = x.select_rows(&keep);
            let yi = DVector::from_iterator(keep.len(), keep.iter().map(|&j| labels[j]));
            let mut state = gp.state();
            state.n_train = keep.len();
            let without = GpModel::from_state(&xi, &yi, &state).unwrap();
            let pred = without.predict(&x.rows(group[0], 1).into_owned());
            let (mu, sd) = (pred.mean[0], (pred.latent_variance[0] + noise).sqrt());
            let z = (D_MAX - mu) / sd;
            let safe = deviations[group[0]] < D_MAX;
            let inside = mu + 2.0 * sd < D_MAX;
            trusted_safe += group.len() * usize::from(safe && inside);
            trusted_unsafe += group.len() * usize::from(!safe && inside);
            log_score += normal_tail(if safe { -z } else { z }).ln() / groups.len() as f64;
        }
        assert_eq!(
            (t.trusted_safe, t.trusted_unsafe),
            (trusted_safe, trusted_unsafe)
        );
        assert!(
            (t.log_score - log_score).abs() < 1e-6,
            "{} vs {log_score}",
            t.log_score
        );
    }

    #[test]
    fn a_cap_replaces_raw_labels_only_when_clearly_better() {
        let raw = [-0.5, -0.4, -0.6, -0.5];
        assert!(clearly_better(&[-0.1, -0.1, -0.2, -0.1], &raw));
        // Better on average, but by less than its noise.
        assert!(!clearly_better(&[-0.1, -0.9, -0.2, -0.7], &raw));
        assert!(!clearly_better(&raw, &raw));
        assert!(!clearly_better(&[-0.1], &[-0.5]));
    }

    #[test]
    fn one_candidate_is_kept_and_judged() {
        let (x, deviations) = world(|a, _| if a < 0.5 { 0.0 } else { 1.0 });
        let c = fit_choosing_label_cap(
            Training {
                x: &x,
                deviations: &deviations,
                trajectories: &own_trajectories(&x),
            },
            at_beta_2(),
            &[Kernel::Matern52],
            &[0.0],
            EstimatorKind::Exact,
            &params(),
        )
        .unwrap();
        assert_eq!(c.label_cap, 0.0);
        assert_eq!(c.trials.len(), 1);
        assert_eq!(c.trials[0].unsafe_transitions, 30);
    }

    #[test]
    fn labels_are_clipped_at_the_cap_and_raw_at_zero() {
        let d = [0.0, 0.05, 0.3, 2.0];
        assert_eq!(capped_labels(&d, 2.0, D_MAX), vec![0.0, 0.05, 0.2, 0.2]);
        assert_eq!(capped_labels(&d, 0.0, D_MAX), d.to_vec());
        assert!((normal_tail(2.0) - 0.02275).abs() < 1e-5);
        assert!((normal_tail(0.0) - 0.5).abs() < 1e-12);
    }

    #[test]
    fn a_kernel_leaves_the_evidences_choice_only_when_clearly_better_held_out() {
        let trial = |kernel, lml, score| KernelTrial {
            kernel,
            log_marginal_likelihood: lml,
            held_out_log_score: Some(score),
        };
        let trials = [
            trial(Kernel::Matern12, 10.0, -0.15),
            trial(Kernel::Matern32, 30.0, -0.30),
            trial(Kernel::Matern52, 50.0, -0.31),
        ];
        let evidence_best = vec![-0.3, -0.2, -0.4, -0.3, -0.35, -0.25];
        // Matérn 1/2 better at every state-action: clearly better, it is kept.
        let clearly = vec![-0.1, -0.1, -0.2, -0.15, -0.2, -0.15];
        // Matérn 3/2 better on average by much less than the spread of the differences.
        let noisy = vec![-0.1, -0.5, -0.1, -0.6, -0.05, -0.4];
        let held = |a: &Vec<f64>, b: &Vec<f64>| {
            vec![
                Some(a.clone()),
                Some(b.clone()),
                Some(evidence_best.clone()),
            ]
        };
        assert_eq!(best_kernel(&trials, &held(&clearly, &noisy)), Some(0));
        assert_eq!(
            best_kernel(&trials, &held(&noisy, &noisy)),
            Some(2),
            "a gain within the noise leaves the likelihood's kernel"
        );
        assert_eq!(
            best_kernel(&trials, &[None, None, None]),
            Some(2),
            "without held-out judgements, the likelihood"
        );
        assert_eq!(best_kernel(&[], &[]), None);
    }

    #[test]
    fn the_sparse_gp_chooses_on_at_most_selection_subset_transitions_and_fits_on_all() {
        let (x, deviations) = dense_world(60, |a, _| if a < 0.5 { 0.0 } else { 0.3 });
        let trajectories = own_trajectories(&x);
        for subset in [200, 250] {
            let c = fit_choosing_label_cap(
                Training {
                    x: &x,
                    deviations: &deviations,
                    trajectories: &trajectories,
                },
                at_beta_2(),
                &[Kernel::Matern52],
                &[2.0, 0.0],
                EstimatorKind::Sparse,
                &params().with_selection_subset(subset),
            )
            .expect("fits");
            // The caps were judged on `subset` of the 300 transitions, the model fitted on all.
            let judged = c.trials.iter().map(|t| t.safe + t.unsafe_transitions);
            assert_eq!(
                judged.collect::<Vec<_>>(),
                vec![subset; 2],
                "{:?}",
                c.trials
            );
            assert!(
                c.phases[0]
                    .phase
                    .starts_with(&format!("on {subset} transitions")),
                "{:?}",
                c.phases
            );
            assert_eq!((c.gp.kind(), c.gp.n_train()), (EstimatorKind::Sparse, 300));
        }
    }

    #[test]
    fn the_kernel_with_the_highest_evidence_is_kept_and_its_fit_returned() {
        // A smooth ramp and a cliff: whichever kernel wins, it is the one whose fit on the
        // first cap's labels has the largest log marginal likelihood — or one judged better
        // held out — and the model returned is fitted with it.
        let worlds = [
            world(|a, b| 0.3 * (a + 0.5 * b)),
            world(|a, _| if a < 0.5 { 0.0 } else { 2.0 }),
        ];
        for (x, deviations) in &worlds {
            let c = fit_choosing_label_cap(
                Training {
                    x,
                    deviations,
                    trajectories: &own_trajectories(x),
                },
                at_beta_2(),
                &Kernel::ALL,
                &[2.0, 0.0],
                EstimatorKind::Exact,
                &params(),
            )
            .expect("fits");
            assert_eq!(c.kernel_trials.len(), 3);
            assert!(
                c.kernel_trials
                    .iter()
                    .all(|t| t.held_out_log_score.is_some_and(f64::is_finite)),
                "{:?}",
                c.kernel_trials
            );
            let by_evidence = c
                .kernel_trials
                .iter()
                .max_by(|a, b| {
                    a.log_marginal_likelihood
                        .total_cmp(&b.log_marginal_likelihood)
                })
                .unwrap();
            let kept = c.gp.hyperparameters().unwrap().kernel;
            let kept_trial = c.kernel_trials.iter().find(|t| t.kernel == kept).unwrap();
            assert!(
                kept == by_evidence.kernel
                    || kept_trial.held_out_log_score > by_evidence.held_out_log_score,
                "{:?}",
                c.kernel_trials
            );
            // The caps were judged with the kept kernel.
            let labels = capped_labels(deviations, c.label_cap, D_MAX);
            let again = GpModel::fit(
                x,
                &DVector::from_vec(labels),
                &gp_params(NoiseMode::Homoscedastic, kept, 0.0, 0, 7)
                    .check()
                    .unwrap(),
            )
            .unwrap();
            let q = DMatrix::from_row_slice(1, 2, &[0.42, 0.5]);
            assert_eq!(c.gp.predict(&q).mean, again.predict(&q).mean);
        }
    }
}
