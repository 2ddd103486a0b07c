//! An experiment's history as the dashboard shows it: its runs (proposals and the trajectories
//! that executed them, trajectories without a proposal) and its learning timeline.

use super::experiments::{check_page, next_offset};
use super::{Result, Service};
use crate::limits::{DEFAULT_PAGE, MAX_TIMELINE_ROWS};
use crate::records::{FitRefusal, IterationStats, ModelSummary, Run};
use crate::settings::DOMAIN_MODEL;
use crate::store::LabelStats;

/// One of an experiment's models of its robot (the domain's own, or a further one) with what
/// its labels of the executed transitions say.
#[derive(Debug, Clone)]
pub struct ModelLabelReport {
    /// Its cost per call, in calls of the domain's model.
    pub cost: f64,
    /// Its kind (`remote`, `linear`, `client`, `built_in`).
    pub kind: &'static str,
    /// What its labels say (its name in `stats.model`).
    pub stats: LabelStats,
}

/// A page of runs with the total count and the next page's offset.
#[derive(Debug, Clone)]
pub struct Runs {
    /// The page, newest first.
    pub items: Vec<Run>,
    /// Runs in all.
    pub total: i64,
    /// The next page's offset, if any.
    pub next: Option<i64>,
}

/// How learning went: per iteration (with its `β_j`) and per model version (with the iteration
/// its data reached).
#[derive(Debug, Clone)]
pub struct LearningTimeline {
    /// Trajectories per iteration.
    pub batch_size: i64,
    /// Planned iterations `J`.
    pub iterations_planned: i64,
    /// `(β_j, statistics)` per iteration with data.
    pub iterations: Vec<(f64, IterationStats)>,
    /// `(iteration, summary)` per model version.
    pub models: Vec<(i64, ModelSummary)>,
    /// Fits refused for the memory budget.
    pub fit_refusals: Vec<FitRefusal>,
}

impl Service {
    /// A page of an experiment's runs, newest first (default page size 100).
    pub async fn runs(&self, id: i64, offset: i64, limit: Option<i64>) -> Result<Runs> {
        check_page(offset, limit)?;
        self.experiment(id).await?;
        let limit = limit.unwrap_or(DEFAULT_PAGE);
        let total = self.store.count_runs(id).await?;
        let items = self.store.runs(id, offset, limit).await?;
        let next = next_offset(offset, items.len(), total);
        Ok(Runs { items, total, next })
    }

    /// The experiment's learning timeline (at most [`MAX_TIMELINE_ROWS`] iterations and as many
    /// model versions).
    pub async fn timeline(&self, id: i64) -> Result<LearningTimeline> {
        let e = self.experiment(id).await?.experiment;
        let l = &e.settings.learning;
        let batch = i64::from(l.batch_size.max(1));
        let stats = self
            .store
            .iteration_stats(id, batch, e.settings.d_max, MAX_TIMELINE_ROWS)
            .await?;
        let models = self.store.model_summaries(id, MAX_TIMELINE_ROWS).await?;
        let fit_refusals = self.store.fit_refusals(id, MAX_TIMELINE_ROWS).await?;
        let beta = |j: i64| l.training_beta(j);
        Ok(LearningTimeline {
            batch_size: batch,
            iterations_planned: i64::from(l.iterations),
            iterations: stats.into_iter().map(|s| (beta(s.iteration), s)).collect(),
            models: models
                .into_iter()
                .map(|m| (l.iteration(m.n_trajectories), m))
                .collect(),
            fit_refusals,
        })
    }

    /// Each of the experiment's models of its robot — the domain's own first, then the further
    /// ones in their order — with what its labels of every stored transition say (excluded
    /// trajectories too: a label is data, not a fit).
    pub async fn model_labels(&self, id: i64) -> Result<(f64, Vec<ModelLabelReport>)> {
        let e = self.experiment(id).await?.experiment;
        let d_max = e.settings.d_max;
        let mut stats = self.store.label_stats(id, d_max).await?;
        let mut take = |name: &str| match stats.iter().position(|s| s.model == name) {
            Some(i) => stats.swap_remove(i),
            None => LabelStats {
                model: name.to_string(),
                n_labelled: 0,
                n_missing: 0,
                mean_deviation: None,
                max_deviation: None,
                share_within_d_max: None,
            },
        };
        let mut reports = vec![ModelLabelReport {
            cost: 1.0,
            kind: e.settings.domain.model_kind(),
            stats: take(DOMAIN_MODEL),
        }];
        for m in e.settings.further_models() {
            reports.push(ModelLabelReport {
                cost: m.cost,
                kind: m.model.kind(),
                stats: take(&m.name),
            });
        }
        Ok((d_max, reports))
    }
}
