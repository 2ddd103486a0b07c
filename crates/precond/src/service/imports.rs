//! [`Service::import`]: a file of logged transitions into an experiment through
//! [`crate::import`] — the implementation `precond import` uses — each trajectory stored as a
//! posted one is (labelled by the experiment's models, under its idempotency key).

use super::work::ExportSlot;
use super::{Error, Result, Service};
use crate::api::TrajectoryRequest;
use crate::import::mapping::{self, Given, Spaces};
use crate::import::table::{self, Format};
use crate::import::{
    Assembly, ImportReport, Part, Reading, Stopped, Stored, dataset_identity, drive, key_part,
};
use crate::limits::MAX_TRANSITIONS;
use std::path::PathBuf;

/// A file to import, as the import route received it.
#[derive(Debug, Clone)]
pub struct ImportFile {
    /// Where the file is (the route spools the body to a temporary file).
    pub path: PathBuf,
    /// Its format: CSV or Parquet (not `Auto`: a body has no extension).
    pub format: Format,
    /// The columns the client named (`None`: found by convention).
    pub given: Given,
    /// The dataset's name, stored in every trajectory's `source.dataset`.
    pub dataset: String,
    /// The dataset's identity in the keys; default [`dataset_identity`] of the name.
    pub dataset_id: Option<String>,
    /// A label stored with every trajectory's source.
    pub label: Option<String>,
    /// Bytes of one trajectory's JSON body past which an episode is split: the server's body
    /// limit, as `precond import` splits for it, so that both store the same parts.
    pub max_body_bytes: usize,
    /// Transitions per trajectory past which an episode is split, when the client asked for
    /// fewer than the server's `--max-transitions` (`precond import --max-transitions`).
    pub max_transitions: Option<usize>,
}

impl Service {
    /// One of the slots for large transfers (model and CSV exports, imports), waiting a few
    /// seconds for one; `429 overloaded` when all stay busy.
    pub async fn transfer_slot(&self) -> Result<ExportSlot> {
        self.work.export_slot().await
    }

    /// Imports a file into experiment `id`: reads it through the mapping on a blocking thread
    /// (at most two trajectories in memory) and stores each trajectory as
    /// [`Service::ingest`] does, under its key (an episode stored before is replayed; one that
    /// changed since is refused). Stops at the first refusal, saying where and what was stored
    /// before it ([`Error::ImportStopped`]). The caller holds a slot for large transfers
    /// ([`Service::transfer_slot`]) from before it received the file.
    pub async fn import(
        &self,
        id: i64,
        file: ImportFile,
        _slot: ExportSlot,
    ) -> Result<ImportReport> {
        let live = self.live(id).await?;
        let spaces = Spaces {
            state: live.domain.state_space().names.clone(),
            action: live.domain.action_space().names.clone(),
            client_side: live.domain.dynamics().client_side(),
        };
        let dataset_id = match &file.dataset_id {
            Some(given) if key_part(given) == *given => given.clone(),
            Some(_) => {
                return Err(Error::validation(
                    "dataset_id",
                    "letters, digits, '.', '_' and '-' only, 1 to 64 characters",
                ));
            }
            None => dataset_identity(&file.dataset),
        };
        let (path, format, given) = (file.path.clone(), file.format, file.given.clone());
        let found = tokio::task::spawn_blocking(move || -> anyhow::Result<_> {
            let (columns, _) = table::columns(&path, format)?;
            let mapping = mapping::resolve(&columns, &spaces, &given)?;
            Ok((columns, mapping, spaces))
        })
        .await
        .map_err(|e| Error::Internal(anyhow::anyhow!("the import's reader failed: {e}")))?;
        let (columns, mapping, spaces) =
            found.map_err(|e| Error::validation("body", format!("{e:#}")))?;
        let assembly = Assembly {
            dataset: file.dataset.clone(),
            dataset_id,
            label: file.label.clone(),
            max_transitions: self
                .work
                .limits()
                .max_transitions
                .min(MAX_TRANSITIONS)
                .min(file.max_transitions.unwrap_or(usize::MAX))
                .max(1),
            max_body_bytes: file.max_body_bytes,
        };
        let reading = Reading {
            path: file.path.clone(),
            format: file.format,
            columns,
            mapping,
            dims: (spaces.state.len(), spaces.action.len()),
            assembly,
        };
        let service = self;
        let store = move |part: Part| async move {
            let Part {
                key,
                source,
                transitions,
                ..
            } = part;
            let n = transitions.len();
            let request = TrajectoryRequest {
                proposal_id: None,
                partial: false,
                source: Some(source),
                transitions,
            };
            let ingested = service.ingest(id, request, Some(key.as_bytes())).await?;
            Ok(Stored {
                id: ingested.record.trajectory_id,
                transitions: n,
                replayed: ingested.replayed,
            })
        };
        drive(reading, store, |_| {})
            .await
            .map_err(|stopped| match stopped {
                Stopped::Storing { stop, error } => Error::ImportStopped {
                    stop: Box::new(stop),
                    error: Box::new(error),
                },
                Stopped::Reading { stop, error } => Error::ImportStopped {
                    stop: Box::new(stop),
                    error: Box::new(Error::validation("body", format!("{error:#}"))),
                },
                Stopped::Reader(e) => {
                    Error::Internal(anyhow::anyhow!("the import's reader failed: {e}"))
                }
            })
    }
}
