//! Looking inside a model version: its `μ` and `σ` on a grid over two components of `(s, a)`
//! (the precondition map) and its leave-one-out calibration (diagnostics).

use super::live::LiveExperiment;
use super::{Error, Result, Service};
use crate::api::{Coverage, PreconditionRates};
use crate::domain::Space;
use crate::limits::{
    DEFAULT_MAP_SIDE, MAX_LATER_TRANSITIONS, MAX_MAP_SIDE, MAX_MAP_TRAINING_POINTS,
};
use crate::mde::{Estimator, ServedModel};
use crate::planning::{Agreement, Precondition};
use crate::records::StoredTransition;
use std::sync::Arc;
use std::time::Instant;

/// What a precondition map asks for, parsed.
#[derive(Debug, Clone)]
pub struct MapRequest {
    /// Horizontal axis, `s.<name>` or `a.<name>`.
    pub x: String,
    /// Vertical axis.
    pub y: String,
    /// The state fixing the other components (default: the state box's centre).
    pub s: Option<Vec<f64>>,
    /// The action fixing the other components (default: the first discrete action or the
    /// action box's centre).
    pub a: Option<Vec<f64>>,
    /// Grid points along `x`.
    pub nx: Option<usize>,
    /// Grid points along `y`.
    pub ny: Option<usize>,
    /// Model version (default: the current one).
    pub version: Option<i64>,
    /// A further model's name: its precondition (default, or `domain`: the domain model's).
    pub model: Option<String>,
}

/// A model version evaluated on a grid.
#[derive(Debug, Clone)]
pub struct PreconditionGrid {
    /// The version evaluated.
    pub model: Arc<ServedModel>,
    /// The experiment's tolerance.
    pub d_max: f64,
    /// The test β of the answering version (see `LiveExperiment::test_beta`).
    pub test_beta: f64,
    /// The fixed state.
    pub s: Vec<f64>,
    /// The fixed action.
    pub a: Vec<f64>,
    /// `(name, coordinates)` of the horizontal axis.
    pub x: (String, Vec<f64>),
    /// `(name, coordinates)` of the vertical axis.
    pub y: (String, Vec<f64>),
    /// `μ`, row-major (`ny` rows of `nx`).
    pub mu: Vec<f64>,
    /// `σ`, laid out as `mu`.
    pub sigma: Vec<f64>,
    /// Training transitions of the version, evenly thinned (with a further model's map, those
    /// it labelled, each with its label as `deviation`).
    pub training: Vec<StoredTransition>,
    /// The further model whose precondition this is (`None`: the domain model's).
    pub further: Option<String>,
}

/// `(z, P(|N(0,1)| ≤ z))` for the coverage table.
const NOMINAL: [(f64, f64); 6] = [
    (0.5, 0.382_924_922_548_026),
    (1.0, 0.682_689_492_137_086),
    (1.5, 0.866_385_597_462_284),
    (2.0, 0.954_499_736_103_642),
    (2.5, 0.987_580_669_348_448),
    (3.0, 0.997_300_203_936_740),
];

/// Summarises predictions `(y_i − μ_i, σ_i)` of `labels` (leave-one-out, or by a model that
/// never saw them): coverage of `μ ± zσ`,
/// RMSE, mean log predictive density, and the precondition `μ + βσ < d_max` against the truth
/// `y < d_max`.
pub fn loo_summary(labels: &[f64], loo: &[(f64, f64)], precondition: Precondition) -> LooSummary {
    let d_max = precondition.d_max();
    let n = labels.len().min(loo.len());
    let share = |count: usize| if n == 0 { 0.0 } else { count as f64 / n as f64 };
    let coverage = NOMINAL
        .iter()
        .map(|&(z, nominal)| Coverage {
            z,
            nominal,
            observed: share(loo.iter().filter(|(r, sd)| r.abs() <= z * sd).count()),
        })
        .collect();
    let rmse = (loo.iter().map(|(r, _)| r * r).sum::<f64>() / n.max(1) as f64).sqrt();
    let mean_log_density = loo
        .iter()
        .map(|(r, sd)| -0.5 * (r / sd).powi(2) - sd.ln() - 0.5 * (2.0 * std::f64::consts::PI).ln())
        .sum::<f64>()
        / n.max(1) as f64;
    let mut agreement = Agreement::default();
    for (y, (r, sd)) in labels.iter().zip(loo) {
        agreement.count(*y, d_max, precondition.inside(y - r, *sd));
    }
    LooSummary {
        n,
        rmse,
        mean_log_density,
        coverage,
        precondition: PreconditionRates {
            beta: precondition.beta(),
            d_max,
            positives: agreement.positives,
            negatives: agreement.negatives,
            true_positives: agreement.true_positives,
            true_negatives: agreement.true_negatives,
            tpr: agreement.tpr(),
            tnr: agreement.tnr(),
        },
    }
}

/// What [`loo_summary`] finds.
#[derive(Debug, Clone, PartialEq)]
pub struct LooSummary {
    /// Labels checked.
    pub n: usize,
    /// Root mean squared leave-one-out error.
    pub rmse: f64,
    /// Mean Gaussian log predictive density.
    pub mean_log_density: f64,
    /// Observed against nominal coverage.
    pub coverage: Vec<Coverage>,
    /// The precondition's rates.
    pub precondition: PreconditionRates,
}

/// Leave-one-out checks of a fitted version, and its judgements of later transitions.
#[derive(Debug, Clone)]
pub struct LooDiagnostics {
    /// The version checked.
    pub model_version: i64,
    /// What leave-one-out found.
    pub summary: LooSummary,
    /// What the version found on the transitions posted after its training set (none: `None`).
    pub later: Option<LooSummary>,
}

/// Where an axis name points: a state (`false`) or action (`true`) component.
fn parse_axis(field: &str, name: &str, state: &Space, action: &Space) -> Result<(bool, usize)> {
    let found = match name.split_once('.') {
        Some(("s", c)) => state.names.iter().position(|n| n == c).map(|i| (false, i)),
        Some(("a", c)) => action.names.iter().position(|n| n == c).map(|i| (true, i)),
        _ => None,
    };
    found.ok_or_else(|| {
        let names: Vec<String> = state
            .names
            .iter()
            .map(|n| format!("s.{n}"))
            .chain(action.names.iter().map(|n| format!("a.{n}")))
            .collect();
        Error::validation(
            field,
            format!("{name:?} is not a component; one of {}", names.join(", ")),
        )
    })
}

/// A fixed vector: the right dimension, finite.
fn check_vector(field: &str, v: &[f64], space: &Space) -> Result<()> {
    if v.len() != space.dim() {
        return Err(Error::validation(
            field,
            format!(
                "expected {} components ({}), got {}",
                space.dim(),
                space.names.join(", "),
                v.len()
            ),
        ));
    }
    if let Some(i) = v.iter().position(|x| !x.is_finite()) {
        return Err(Error::validation(
            field,
            format!("component {i} ({}) is not a finite number", space.names[i]),
        ));
    }
    Ok(())
}

fn side(field: &str, n: Option<usize>) -> Result<usize> {
    let n = n.unwrap_or(DEFAULT_MAP_SIDE);
    if !(2..=MAX_MAP_SIDE).contains(&n) {
        return Err(Error::validation(
            field,
            format!("must be between 2 and {MAX_MAP_SIDE}"),
        ));
    }
    Ok(n)
}

fn centre(space: &Space) -> Vec<f64> {
    space
        .low
        .iter()
        .zip(&space.high)
        .map(|(l, h)| 0.5 * (l + h))
        .collect()
}

/// `n` evenly spaced values from `low` to `high`, both included.
fn linspace(low: f64, high: f64, n: usize) -> Vec<f64> {
    (0..n)
        .map(|i| low + (high - low) * i as f64 / (n - 1) as f64)
        .collect()
}

/// Every `⌈n / max⌉`-th element, at most `max`.
fn thin<T>(items: Vec<T>, max: usize) -> Vec<T> {
    let stride = items.len().div_ceil(max.max(1)).max(1);
    items.into_iter().step_by(stride).collect()
}

impl Service {
    /// Model version `version` of `live` (`None`: the one answering). An older fitted version
    /// is rebuilt from its stored state (one factorisation, `O(n³)` time and `n²` memory), so
    /// asking for one takes a slot of the work gate like a search, under the same deadline
    /// counted from `arrived` (`503` when it passes while waiting, `429` when the queue is
    /// full): concurrent rebuilds are bounded by `--max-concurrent-plans`. The rebuild runs in
    /// a task of its own that holds the slot until it ends, so a client that goes away does not
    /// free the slot of a rebuild still running. The current version and the prior need no
    /// slot.
    pub(super) async fn model_version(
        &self,
        live: &Arc<LiveExperiment>,
        version: Option<i64>,
        arrived: Instant,
    ) -> Result<Arc<ServedModel>> {
        let current = live.model().version;
        let Some(older) = version.filter(|v| *v != current && *v != 0) else {
            return live.model_at(&self.store, version).await;
        };
        let (slot, _deadline) = self.work.plan_slot(live.id, arrived).await?;
        let (live, store) = (live.clone(), self.store.clone());
        tokio::spawn(async move {
            let _slot = slot;
            live.model_at(&store, Some(older)).await
        })
        .await
        .map_err(|e| Error::Internal(anyhow::Error::new(e).context("rebuilding a model version")))?
    }

    /// `μ` and `σ` of a model version on a grid over two components of `(s, a)`, the other
    /// components fixed; with the version's training transitions (thinned) to draw on it. The
    /// grid is evaluated in an evaluation slot of the work gate
    /// ([`WorkGate::evaluation_slot`](super::WorkGate::evaluation_slot)), under the same
    /// deadline as a rebuild.
    pub async fn precondition_map(&self, id: i64, request: MapRequest) -> Result<PreconditionGrid> {
        let arrived = Instant::now();
        let live = self.live(id).await?;
        let domain = live.domain.clone();
        let (state, action) = (domain.state_space(), domain.action_space());
        let x_axis = parse_axis("x", &request.x, state, action)?;
        let y_axis = parse_axis("y", &request.y, state, action)?;
        if x_axis == y_axis {
            return Err(Error::validation("y", "must differ from x"));
        }
        let (nx, ny) = (side("nx", request.nx)?, side("ny", request.ny)?);
        let s = request.s.unwrap_or_else(|| centre(state));
        check_vector("s", &s, state)?;
        let a = request.a.unwrap_or_else(|| match &action.values {
            Some(values) if !values.is_empty() => values[0].clone(),
            _ => centre(action),
        });
        check_vector("a", &a, action)?;
        let model = self.model_version(&live, request.version, arrived).await?;
        let further = request
            .model
            .filter(|name| name != crate::settings::DOMAIN_MODEL)
            .map(|name| {
                let k = live.further_with_estimator(&model, "model", &name)?;
                let m = live.models[k].model.clone();
                if m.client_side() && domain.features_use_prediction() {
                    return Err(Error::validation(
                        "model",
                        format!(
                            "{name:?} is the client's own model and the features read its \
                             prediction, which only the client has: ask POST …/precondition \
                             with its predictions instead"
                        ),
                    ));
                }
                Ok::<_, Error>((name, m))
            })
            .transpose()?;
        let further_model = further.as_ref().map(|(_, m)| m.clone());
        let further_name = further.map(|(name, _)| name);
        let bounds = |(is_action, i): (bool, usize)| {
            let space = if is_action { action } else { state };
            (space.low[i], space.high[i])
        };
        let (xl, xh) = bounds(x_axis);
        let (yl, yh) = bounds(y_axis);
        let (xs, ys) = (linspace(xl, xh, nx), linspace(yl, yh, ny));
        let dim = domain.feature_dim();
        let (grid_s, grid_a, grid_xs, grid_ys) = (s.clone(), a.clone(), xs.clone(), ys.clone());
        let evaluated = model.clone();
        let evaluated_name = further_name.clone();
        let slot = self.work.evaluation_slot(arrived).await?;
        let answers = Self::blocking(move || {
            // Held by the evaluation, not the request: freed when the evaluation ends.
            let _slot = slot;
            let (mut ps, mut pa) = (grid_s, grid_a);
            let set = |(is_action, i): (bool, usize), v: f64, ps: &mut [f64], pa: &mut [f64]| {
                if is_action { pa[i] = v } else { ps[i] = v }
            };
            let mut points = Vec::with_capacity(nx * ny);
            for &yv in &grid_ys {
                for &xv in &grid_xs {
                    set(x_axis, xv, &mut ps, &mut pa);
                    set(y_axis, yv, &mut ps, &mut pa);
                    points.push((ps.clone(), pa.clone()));
                }
            }
            let dynamics = match &further_model {
                Some(m) => m.as_ref(),
                None => domain.dynamics(),
            };
            let predicted = crate::domain::predictions_of(domain.as_ref(), dynamics, &points)?;
            let mut features = Vec::with_capacity(nx * ny * dim);
            for ((s, a), next) in points.iter().zip(&predicted) {
                features.extend(domain.features(s, a, next));
            }
            Ok::<_, Error>(match &evaluated_name {
                Some(name) => evaluated
                    .further(name)
                    .map(|f| f.estimator.answer(&features, dim))
                    .unwrap_or_default(),
                None => evaluated.answer(&features, dim),
            })
        })
        .await??;
        if answers
            .iter()
            .any(|p| !(p.mu.is_finite() && p.sigma.is_finite()))
        {
            return Err(Error::Internal(anyhow::anyhow!(
                "the model answered a non-finite deviation on the map's grid"
            )));
        }
        let n_train = model.n_train() as i64;
        let mut training = if n_train > 0 {
            self.store
                .transitions_outside(
                    id,
                    &LiveExperiment::trained_outside(&model),
                    0,
                    Some(n_train),
                )
                .await?
        } else {
            Vec::new()
        };
        if let (Some(name), Some(first), Some(last)) =
            (&further_name, training.first(), training.last())
        {
            // The further model's own labels of the version's training transitions.
            let labels: std::collections::HashMap<i64, f64> = self
                .store
                .model_labels(id, first.id, last.id)
                .await?
                .into_iter()
                .filter(|(_, l)| &l.model == name)
                .filter_map(|(t, l)| Some((t, l.deviation?)))
                .collect();
            training.retain_mut(|t| match labels.get(&t.id) {
                Some(&d) => {
                    t.deviation = d;
                    true
                }
                None => false,
            });
        }
        let training = thin(training, MAX_MAP_TRAINING_POINTS);
        Ok(PreconditionGrid {
            d_max: live.settings.d_max,
            test_beta: live.test_beta(&model),
            s,
            a,
            x: (request.x, xs),
            y: (request.y, ys),
            mu: answers.iter().map(|p| p.mu).collect(),
            sigma: answers.iter().map(|p| p.sigma).collect(),
            training,
            model,
            further: further_name,
        })
    }

    /// Leave-one-out predictions of every training label of a fitted version (default: the
    /// current one) from the others, and its answers on the transitions posted after its
    /// training set, evaluated in an evaluation slot of the work gate as a map is; `Conflict`
    /// for the prior, which has no labels.
    pub async fn diagnostics(
        &self,
        id: i64,
        version: Option<i64>,
        beta: Option<f64>,
    ) -> Result<LooDiagnostics> {
        let arrived = Instant::now();
        let live = self.live(id).await?;
        let model = self.model_version(&live, version, arrived).await?;
        let precondition = live.precondition_for(&model, beta)?;
        let Estimator::Fitted(gp) = &model.estimator else {
            return Err(Error::Conflict(format!(
                "model version {} is the prior: there are no training labels to check",
                model.version
            )));
        };
        let outside = LiveExperiment::trained_outside(&model);
        let labels = self
            .store
            .first_deviations(id, &outside, gp.n_train() as i64)
            .await?;
        let later = self
            .store
            .transitions_after_first(id, &outside, labels.len() as i64, MAX_LATER_TRANSITIONS)
            .await?;
        let dim = live.domain.feature_dim();
        let mut features = Vec::with_capacity(later.len() * dim);
        for t in &later {
            features.extend(live.domain.features(&t.s, &t.a, &t.s_pred));
        }
        let evaluated = model.clone();
        let slot = self.work.evaluation_slot(arrived).await?;
        // One evaluation: leave-one-out on the version's factor, and its answers on the later
        // transitions (none: no answers).
        let (loo, answers) = Self::blocking(move || {
            let _slot = slot;
            let loo = match &evaluated.estimator {
                Estimator::Fitted(gp) => gp.leave_one_out(),
                Estimator::Prior(_) => None,
            };
            let answers = if features.is_empty() || loo.is_none() {
                Vec::new()
            } else {
                evaluated.answer(&features, dim)
            };
            (loo, answers)
        })
        .await?;
        let loo = loo.ok_or_else(|| {
            Error::Conflict(format!(
                "model version {} is a sparse GP, which has no closed-form leave-one-out: \
                 diagnostics need an exact GP version",
                model.version
            ))
        })?;
        if labels.len() != loo.len() {
            return Err(Error::Internal(anyhow::anyhow!(
                "model {} has {} training points but {} labels are stored",
                model.version,
                loo.len(),
                labels.len()
            )));
        }
        let later = if later.is_empty() {
            None
        } else {
            let labels: Vec<f64> = later.iter().map(|t| t.deviation).collect();
            // As residuals `(y − μ, σ)`, the form `loo_summary` reads.
            let residuals: Vec<(f64, f64)> = labels
                .iter()
                .zip(&answers)
                .map(|(y, a)| (y - a.mu, a.sigma))
                .collect();
            if residuals
                .iter()
                .any(|(r, sd)| !(r.is_finite() && sd.is_finite()))
            {
                return Err(Error::Internal(anyhow::anyhow!(
                    "the model answered a non-finite deviation on a later transition"
                )));
            }
            Some(loo_summary(&labels, &residuals, precondition))
        };
        Ok(LooDiagnostics {
            model_version: model.version,
            summary: loo_summary(&labels, &loo, precondition),
            later,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loo_summary_counts_coverage_and_rates() {
        // Residuals of 0.5σ, 1.5σ, 2.5σ and 0 with σ = 0.1.
        let labels = [0.0, 0.3, 0.05, 0.2];
        let loo = [(0.05, 0.1), (0.15, 0.1), (-0.25, 0.1), (0.0, 0.1)];
        let s = loo_summary(&labels, &loo, Precondition::new(1.0, 0.2).unwrap());
        assert_eq!(s.n, 4);
        let observed: Vec<f64> = s.coverage.iter().map(|c| c.observed).collect();
        assert_eq!(observed, vec![0.5, 0.5, 0.75, 0.75, 1.0, 1.0]);
        // μ₋ᵢ = y − r: −0.05, 0.15, 0.3, 0.2; upper = μ + 0.1: 0.05, 0.25, 0.4, 0.3.
        let p = &s.precondition;
        assert_eq!((p.positives, p.negatives), (2, 2));
        assert_eq!((p.true_positives, p.true_negatives), (1, 2));
        assert_eq!((p.tpr, p.tnr), (Some(0.5), Some(1.0)));
        let rmse = ((0.05f64.powi(2) + 0.15f64.powi(2) + 0.25f64.powi(2)) / 4.0).sqrt();
        assert!((s.rmse - rmse).abs() < 1e-12);
    }

    #[test]
    fn thinning_keeps_at_most_the_bound_evenly() {
        let kept = thin((0..4500).collect::<Vec<_>>(), 2000);
        assert!(kept.len() <= 2000);
        assert_eq!(&kept[..3], &[0, 3, 6]);
        assert_eq!(thin(vec![1, 2], 2000), vec![1, 2]);
    }
}
