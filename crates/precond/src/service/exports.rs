//! Large answers, prepared for streaming: a model version's export and every transition of an
//! experiment as CSV. Each holds an export slot of the work gate
//! ([`WorkGate::export_slot`](super::WorkGate::export_slot)) from the moment it is granted until
//! the writer drops it, so the memory all of them hold together is bounded by the slots,
//! whatever the number of clients; the writer (the HTTP layer) turns them into bytes a chunk
//! at a time.

use super::{Error, Result, Service};
use crate::domain::Domain;
use crate::mde::{Estimator, ExportedModel, ServedModel};
use crate::records::StoredTransition;
use crate::service::ExportSlot;
use crate::settings::DOMAIN_MODEL;
use crate::store::Store;
use std::sync::Arc;
use std::time::Instant;

/// Transitions read from the database at a time while a CSV export is written: what one
/// export holds of the experiment's data.
pub const EXPORT_PAGE: i64 = 2000;

/// A model version to export, in its slot.
pub struct ModelExport {
    /// Held until the export is written.
    pub slot: ExportSlot,
    id: i64,
    model: Arc<ServedModel>,
    /// The further model whose estimator to export (`None`: the domain model's).
    further: Option<String>,
    domain: Arc<dyn Domain>,
    d_max: f64,
    test_beta: f64,
}

impl ModelExport {
    /// The exported document (its size is the model's: the training inputs, and for the exact
    /// GP the packed `L⁻¹`). Blocking: call it on the writer's thread.
    pub fn build(&self) -> Result<ExportedModel> {
        let domain = self.domain.as_ref();
        match &self.further {
            None => ExportedModel::of(self.id, &self.model, domain, self.d_max, self.test_beta),
            Some(name) => ExportedModel::of_further(
                self.id,
                &self.model,
                name,
                domain,
                self.d_max,
                self.test_beta,
            ),
        }
        .ok_or_else(|| Error::Internal(anyhow::anyhow!("a fitted version exported as the prior")))
    }

    /// Numbers the document holds, about: what its size (some 20 bytes a number as JSON) and
    /// the memory of [`ModelExport::build`] (8 bytes a number) follow.
    pub fn numbers(&self) -> usize {
        let estimator = match &self.further {
            None => &self.model.estimator,
            Some(name) => match self.model.further(name) {
                Some(f) => &f.estimator,
                None => return 0,
            },
        };
        match estimator {
            Estimator::Fitted(gp) => {
                let (n, d) = (gp.n_train(), self.domain.feature_map().dim());
                n * d + n * (n + 1) / 2
            }
            Estimator::Prior(_) => 0,
        }
    }
}

/// Transitions to write as CSV, page by page, in their slot.
pub struct TransitionsExport {
    /// Held until the export is written.
    pub slot: ExportSlot,
    store: Store,
    id: i64,
    /// The domain, for the columns' names.
    pub domain: Arc<dyn Domain>,
    /// The experiment's further models, whose deviations follow the domain model's.
    pub models: Vec<String>,
    /// The last transition id written so far.
    cursor: i64,
    /// The last transition id to write (fixed when the export starts: transitions posted
    /// meanwhile are not in it).
    upto: i64,
    /// The cursor of the following page when the request's `limit` cut the export short.
    pub next: Option<i64>,
}

impl TransitionsExport {
    /// The next page of at most [`EXPORT_PAGE`] transitions, empty at the end.
    pub async fn next_page(&mut self) -> Result<Vec<StoredTransition>> {
        if self.cursor >= self.upto {
            return Ok(Vec::new());
        }
        let mut page = self
            .store
            .transitions_between(self.id, self.cursor, self.upto, EXPORT_PAGE)
            .await?;
        super::ingest::attach_labels(&self.store, self.id, &self.models, &mut page).await?;
        if let Some(last) = page.last() {
            self.cursor = last.id;
        } else {
            self.cursor = self.upto;
        }
        Ok(page)
    }
}

impl Service {
    /// A fitted version (default: the current one) ready to export in an export slot;
    /// `Conflict` for the prior, which has nothing fitted to export. With `further`, the
    /// estimator of that one of the experiment's further models in the version (`domain`: the
    /// domain model's); `Conflict` when the version holds none of it.
    pub async fn prepare_model_export(
        &self,
        id: i64,
        version: Option<i64>,
        further: Option<&str>,
    ) -> Result<ModelExport> {
        let arrived = Instant::now();
        if let Some(v) = version.filter(|v| *v < 0) {
            return Err(Error::validation(
                "version",
                format!("{v} is not a model version (they are numbered from 0, the prior)"),
            ));
        }
        let live = self.live(id).await?;
        let model = self.model_version(&live, version, arrived).await?;
        if matches!(model.estimator, Estimator::Prior(_)) {
            return Err(Error::Conflict(format!(
                "model version {} is the prior: there is no fitted model to export yet \
                 (post trajectories or refit first)",
                model.version
            )));
        }
        let further = further.filter(|n| *n != DOMAIN_MODEL);
        let test_beta = match further {
            None => live.test_beta(&model),
            Some(name) => {
                if !live.models.iter().any(|m| m.name == name) {
                    return Err(Error::validation(
                        "model",
                        format!("the experiment has no further model named {name:?}"),
                    ));
                }
                if model.further(name).is_none() {
                    return Err(Error::Conflict(format!(
                        "model version {} holds no estimator of {name:?}: one is fitted by the \
                         first fit after it labelled a transition",
                        model.version
                    )));
                }
                live.settings.learning.test_beta
            }
        };
        let slot = self.work.export_slot().await?;
        Ok(ModelExport {
            slot,
            id,
            further: further.map(str::to_string),
            domain: live.domain.clone(),
            d_max: live.settings.d_max,
            test_beta,
            model,
        })
    }

    /// The transitions of experiment `id` after `after` (at most `limit`, else all stored
    /// now), ready to write page by page in an export slot.
    pub async fn prepare_transitions_export(
        &self,
        id: i64,
        after: i64,
        limit: Option<i64>,
    ) -> Result<TransitionsExport> {
        let experiment = self.experiment(id).await?;
        let (upto, next) = self.store.export_bounds(id, after, limit).await?;
        let slot = self.work.export_slot().await?;
        Ok(TransitionsExport {
            slot,
            store: self.store.clone(),
            id,
            domain: experiment.domain,
            models: experiment.experiment.settings.further_model_names(),
            cursor: after,
            upto,
            next,
        })
    }
}
