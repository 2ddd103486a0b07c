//! [`Service::import`]: a file of logged transitions into an experiment through
//! [`crate::import`] — the implementation `precond import` uses — each trajectory stored as a
//! posted one is (labelled by the experiment's models, under its idempotency key).

use super::ingest::check_source;
use super::work::ExportSlot;
use super::{Error, Result, Service};
use crate::api::TrajectoryRequest;
use crate::api::TrajectorySource;
use crate::import::mapping::{self, Given, Spaces};
use crate::import::table::{self, Format};
use crate::import::{Assembly, ImportReport, Part, Reading, Stopped, Stored, drive};
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
    /// The dataset's identity in the keys, as [`check_import`] gave it.
    pub dataset_id: String,
    /// A label stored with every trajectory's source.
    pub label: Option<String>,
    /// Bytes of one trajectory's JSON body past which an episode is split: the server's body
    /// limit, as `precond import` splits for it, so that both store the same parts.
    pub max_body_bytes: usize,
    /// Transitions per trajectory past which an episode is split, when the client asked for
    /// fewer than the server's `--max-transitions` (`precond import --max-transitions`).
    pub max_transitions: Option<usize>,
}

/// Checks what names an import's trajectories before its file is read — the dataset's name
/// and the label as every trajectory's `source` needs them, the dataset id in the keys —
/// naming the query parameter at fault; returns the dataset id ([`dataset_id`]).
pub fn check_import(
    dataset: &str,
    label: Option<&str>,
    dataset_id: Option<&str>,
) -> Result<String> {
    check_source(TrajectorySource {
        dataset: dataset.to_string(),
        episode: None,
        first_step: None,
        label: label.map(str::to_string),
    })
    .map_err(|e| match e {
        Error::Validation { field, reason } => Error::Validation {
            field: field.trim_start_matches("source.").to_string(),
            reason,
        },
        other => other,
    })?;
    crate::import::dataset_id(dataset_id, dataset)
        .map_err(|reason| Error::validation("dataset_id", reason))
}

/// The error of a file the import could not read: its own fault (`422` naming `body`), or the
/// server's when reading its temporary copy failed (an I/O error: a full disk, too many open
/// files), which no change to the file would mend. A file that ends too soon or holds what is
/// no text is the file's fault, though the readers say so as I/O errors.
fn unreadable(e: anyhow::Error) -> Error {
    use std::io::ErrorKind::{InvalidData, UnexpectedEof};
    let server = e
        .chain()
        .filter_map(|c| c.downcast_ref::<std::io::Error>())
        .find(|io| !matches!(io.kind(), UnexpectedEof | InvalidData));
    match server {
        Some(io) => Error::from_io(
            std::io::Error::new(io.kind(), io.to_string()),
            "reading the import's temporary file",
        ),
        None => Error::validation("body", format!("{e:#}")),
    }
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
        let (path, format, given) = (file.path.clone(), file.format, file.given.clone());
        let found = tokio::task::spawn_blocking(move || -> anyhow::Result<_> {
            let (columns, _) = table::columns(&path, format)?;
            let mapping = mapping::resolve(&columns, &spaces, &given)?;
            Ok((columns, mapping, spaces))
        })
        .await
        .map_err(|e| Error::Internal(anyhow::anyhow!("the import's reader failed: {e}")))?;
        let (columns, mapping, spaces) = found.map_err(unreadable)?;
        let assembly = Assembly {
            dataset: file.dataset.clone(),
            dataset_id: file.dataset_id.clone(),
            label: file.label.clone(),
            // The server's limit (within 1 and MAX_TRANSITIONS, checked at start), or fewer.
            max_transitions: self
                .work
                .limits()
                .max_transitions
                .min(file.max_transitions.unwrap_or(usize::MAX)),
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
                    error: Box::new(unreadable(error)),
                },
                Stopped::Reader(e) => {
                    Error::Internal(anyhow::anyhow!("the import's reader failed: {e}"))
                }
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_unreadable_file_is_its_own_fault_unless_reading_it_failed() {
        let bad_row = anyhow::anyhow!("s_y: NaN is not a finite number").context("line 3");
        assert!(matches!(
            unreadable(bad_row),
            Error::Validation { field, reason } if field == "body" && reason.starts_with("line 3: s_y")
        ));
        let io = anyhow::Error::new(std::io::Error::other("too many open files"))
            .context("opening the file");
        assert!(matches!(unreadable(io), Error::Internal(_)));
        let full = anyhow::Error::new(std::io::Error::from(std::io::ErrorKind::StorageFull));
        assert!(matches!(unreadable(full), Error::StorageFull(_)));
        let short = anyhow::Error::new(std::io::Error::from(std::io::ErrorKind::UnexpectedEof))
            .context("not a readable Parquet file");
        assert!(matches!(unreadable(short), Error::Validation { .. }));
    }

    #[test]
    fn an_imports_names_are_checked_as_the_query_names_them() {
        assert_eq!(
            check_import("logs", Some("teleop"), None).unwrap(),
            crate::import::dataset_identity("logs")
        );
        assert_eq!(check_import("logs", None, Some("run-3")).unwrap(), "run-3");
        for (dataset, label, id, field) in [
            ("", None, None, "dataset"),
            ("logs", Some("x".repeat(1001)), None, "label"),
            ("logs", None, Some("a/b"), "dataset_id"),
        ] {
            let e = check_import(dataset, label.as_deref(), id).unwrap_err();
            assert!(
                matches!(&e, Error::Validation { field: f, .. } if f == field),
                "{e}"
            );
        }
    }
}
