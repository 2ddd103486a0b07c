//! Logged transitions (CSV or Parquet) into trajectories: the one implementation of an import,
//! used by the import route (`POST /v1/experiments/{id}/imports`, the file as the body) and by
//! `precond import` (which reads files where it runs and posts the trajectories).
//!
//! Each episode of a file becomes one trajectory (or several: see below), with its provenance
//! (`source`: the dataset, the episode, the step of the episode it starts at, a label). Columns
//! are found by convention or named ([`mapping`]); without a next-state column, a transition's
//! next state is the next row's state within the episode (LeRobot's frames). Files are read as
//! a stream ([`table`]): CSV row by row, Parquet row group by row group.
//!
//! **Idempotent, per episode.** Each trajectory is stored under the key
//! `import-<dataset id>-<episode>-<part>`, where the dataset id is the first 16 hex digits of
//! the SHA-256 of the dataset's name ([`dataset_identity`]). The key does not depend on the
//! file's bytes: importing again — after an interruption, after the log grew, after a bad line
//! was fixed — stores only the episodes not stored yet, and an episode whose content, mapping
//! or label changed since it was stored is refused by name rather than stored twice.
//!
//! **Limits.** An episode longer than the server's transitions per trajectory, or whose body
//! would pass the body limit, is split into consecutive trajectories, each saying its first
//! step.

pub mod mapping;
pub mod table;

use crate::api::TrajectorySource;
use crate::domain::Transition;
use anyhow::bail;
use mapping::{Mapping, RowValues};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::HashSet;
use std::path::{Path, PathBuf};
use table::{Cell, Column, Format};

/// What an import did, per file and in all.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct ImportReport {
    /// Episodes read (with at least one transition).
    pub episodes: usize,
    /// Trajectories posted (an episode split in parts posts several).
    pub trajectories: usize,
    /// Of those, stored by this run.
    pub created: usize,
    /// Of those, already stored by an earlier run (replayed; nothing stored).
    pub replayed: usize,
    /// Transitions in the posted trajectories.
    pub transitions: usize,
    /// Episodes split into several trajectories.
    pub split_episodes: usize,
    /// Episodes skipped: a single frame, no transition (frames without a next-state column).
    pub skipped_episodes: usize,
    /// The trajectories posted (stored now or found stored), in the file's order: the first
    /// [`MAX_REPORTED_IDS`] of them (`trajectories` counts all), so that a report's size is
    /// bounded whatever the file holds.
    #[schemars(length(max = MAX_REPORTED_IDS))]
    pub trajectory_ids: Vec<i64>,
}

/// Trajectory ids an [`ImportReport`] lists at most (800 KB of them).
pub const MAX_REPORTED_IDS: usize = 100_000;

impl ImportReport {
    /// Counts one stored trajectory `id` of `transitions` transitions starting at
    /// `first_step` of its episode (0: a new episode), stored now or found stored
    /// (`replayed`).
    pub fn stored(&mut self, id: i64, first_step: Option<i64>, transitions: usize, replayed: bool) {
        if self.trajectory_ids.len() < MAX_REPORTED_IDS {
            self.trajectory_ids.push(id);
        }
        self.trajectories += 1;
        self.transitions += transitions;
        if first_step == Some(0) {
            self.episodes += 1;
        }
        if replayed {
            self.replayed += 1;
        } else {
            self.created += 1;
        }
    }

    /// Adds another file's report to this one.
    pub fn add(&mut self, o: &Self) {
        self.episodes += o.episodes;
        self.trajectories += o.trajectories;
        self.created += o.created;
        self.replayed += o.replayed;
        self.transitions += o.transitions;
        self.split_episodes += o.split_episodes;
        self.skipped_episodes += o.skipped_episodes;
        let room = MAX_REPORTED_IDS.saturating_sub(self.trajectory_ids.len());
        self.trajectory_ids
            .extend(o.trajectory_ids.iter().take(room).copied());
    }
}

/// Where an import stopped part-way, and what it stored before: the `import` of the error's
/// `details` (beside the error's own), so that a client can say which episode was refused.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct ImportStop {
    /// The episode (`source.episode`) of the trajectory that was refused; `null` when the
    /// file could not be read further.
    pub episode: Option<i64>,
    /// The step of that episode the refused trajectory started at; `null` likewise.
    pub first_step: Option<i64>,
    /// What the import stored before it stopped (importing again skips it).
    pub stored_before: ImportReport,
}

impl std::fmt::Display for ImportStop {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match (self.episode, self.first_step) {
            (Some(e), Some(k)) => write!(f, "episode {e} from step {k}"),
            _ => f.write_str("reading the file"),
        }
    }
}

/// One trajectory to store: a whole episode or a part of it.
#[derive(Debug)]
pub struct Part {
    /// Its idempotency key, `import-<dataset id>-<episode>-<part>`.
    pub key: String,
    /// Where it comes from.
    pub source: TrajectorySource,
    /// Its transitions, in order.
    pub transitions: Vec<Transition>,
    /// Rows of the file this part consumed (for progress).
    pub rows: u64,
}

/// What the reader hands on, in the file's order.
#[derive(Debug)]
enum Message {
    /// A trajectory to store.
    Part(Part),
    /// An episode was split (its value, its transitions, its parts).
    Split(String, usize, usize),
    /// An episode had no transition.
    Skipped,
}

/// The dataset's identity in the idempotency keys: the first 16 hex digits of the SHA-256 of
/// its name (the Python client's `import_file` computes the same, so either tool recognises
/// the other's imports).
pub fn dataset_identity(name: &str) -> String {
    Sha256::digest(name.as_bytes())[..8]
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// The dataset's identity in the keys: `given` when it is plain (letters, digits, `.`, `_`,
/// `-`; 1 to 64 characters), else the reason it is refused; without one, [`dataset_identity`]
/// of the dataset's `name`.
pub fn dataset_id(given: Option<&str>, name: &str) -> Result<String, String> {
    match given {
        Some(id) if key_part(id) == id => Ok(id.to_string()),
        Some(id) => Err(format!(
            "letters, digits, '.', '_' and '-' only, 1 to 64 characters, got {id:?}"
        )),
        None => Ok(dataset_identity(name)),
    }
}

/// The episode's part of an idempotency key: its value when short and plain, else a hash.
pub fn key_part(value: &str) -> String {
    let plain = !value.is_empty()
        && value.len() <= 64
        && value
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"._-".contains(&b));
    if plain {
        value.to_string()
    } else {
        let d = Sha256::digest(value.as_bytes());
        format!(
            "h{}",
            d[..8]
                .iter()
                .map(|b| format!("{b:02x}"))
                .collect::<String>()
        )
    }
}

/// An episode's value as text (integral numbers without a fraction) and as `source.episode`:
/// the value when it is a whole number ≥ 0, else the episode's position in the file.
fn episode_of(cell: Option<&Cell>, ordinal: usize) -> (String, i64) {
    match cell {
        Some(Cell::Number(x)) if x.fract() == 0.0 && *x >= 0.0 && *x < 9.0e15 => {
            (format!("{}", *x as i64), *x as i64)
        }
        Some(Cell::Number(x)) => (x.to_string(), ordinal as i64),
        Some(Cell::Text(t)) => (t.clone(), ordinal as i64),
        _ => ("0".into(), ordinal as i64),
    }
}

/// Builds an episode's trajectories from its rows, splitting at the limits.
struct Assembler<'a> {
    dataset: &'a str,
    dataset_id: &'a str,
    label: Option<&'a str>,
    max_transitions: usize,
    max_body: usize,
    send: &'a mut dyn FnMut(Message) -> anyhow::Result<()>,
    seen: HashSet<String>,
    /// The current episode: its text, `source.episode`.
    episode: Option<(String, i64)>,
    ordinal: usize,
    previous: Option<RowValues>,
    buffer: Vec<Transition>,
    bytes: usize,
    rows: u64,
    first_step: usize,
    parts: usize,
    length: usize,
}

impl Assembler<'_> {
    fn row(&mut self, row: RowValues) -> anyhow::Result<()> {
        let value = episode_of(row.episode.as_ref(), self.ordinal);
        if self.episode.as_ref().map(|e| &e.0) != Some(&value.0) {
            self.end_episode()?;
            if !self.seen.insert(value.0.clone()) {
                bail!(
                    "episode {} appears again after another episode: sort the file by episode \
                     (an episode's rows must be consecutive)",
                    value.0
                );
            }
            self.ordinal += 1;
            self.episode = Some(value);
        }
        self.rows += 1;
        let transition = match (&row.s_next, self.previous.take()) {
            (Some(next), _) => Some(Transition {
                s: row.s.clone(),
                a: row.a.clone(),
                s_next: next.clone(),
                s_pred: row.s_pred.clone(),
                predictions: None,
            }),
            (None, Some(prev)) => Some(Transition {
                s: prev.s,
                a: prev.a,
                s_next: row.s.clone(),
                s_pred: prev.s_pred,
                predictions: None,
            }),
            (None, None) => None,
        };
        if row.s_next.is_none() {
            self.previous = Some(row);
        }
        if let Some(t) = transition {
            let size = serde_json::to_string(&t).map_or(0, |j| j.len() + 1);
            if !self.buffer.is_empty()
                && (self.buffer.len() >= self.max_transitions || self.bytes + size > self.max_body)
            {
                self.flush()?;
            }
            self.bytes += size;
            self.buffer.push(t);
        }
        Ok(())
    }

    fn flush(&mut self) -> anyhow::Result<()> {
        let Some((text, episode)) = self.episode.clone() else {
            return Ok(());
        };
        let transitions = std::mem::take(&mut self.buffer);
        let n = transitions.len();
        let part = Part {
            key: format!(
                "import-{}-{}-{}",
                self.dataset_id,
                key_part(&text),
                self.parts
            ),
            source: TrajectorySource {
                dataset: self.dataset.to_string(),
                episode: Some(episode),
                first_step: Some(self.first_step as i64),
                label: self.label.map(str::to_string),
            },
            transitions,
            rows: std::mem::take(&mut self.rows),
        };
        (self.send)(Message::Part(part))?;
        self.first_step += n;
        self.length += n;
        self.parts += 1;
        self.bytes = 0;
        Ok(())
    }

    fn end_episode(&mut self) -> anyhow::Result<()> {
        if self.episode.is_none() {
            return Ok(());
        }
        if !self.buffer.is_empty() {
            self.flush()?;
        }
        let text = self.episode.take().map(|e| e.0).unwrap_or_default();
        if self.parts == 0 {
            (self.send)(Message::Skipped)?;
        } else if self.parts > 1 {
            (self.send)(Message::Split(text, self.length, self.parts))?;
        }
        self.previous = None;
        self.first_step = 0;
        self.parts = 0;
        self.length = 0;
        self.bytes = 0;
        self.rows = 0;
        Ok(())
    }
}

/// How the rows of a file become trajectories: the dataset they belong to and the limits of
/// one trajectory.
#[derive(Debug, Clone)]
pub struct Assembly {
    /// The dataset's name, stored in every trajectory's `source.dataset`.
    pub dataset: String,
    /// The dataset's identity in the keys ([`dataset_identity`] of the name by default).
    pub dataset_id: String,
    /// A free-form label stored with every trajectory's source.
    pub label: Option<String>,
    /// Transitions per trajectory: longer episodes are split.
    pub max_transitions: usize,
    /// Bytes of one trajectory's JSON body: larger episodes are split.
    pub max_body_bytes: usize,
}

/// Reads the file's rows through the mapping and hands each finished trajectory (and what
/// happened to each episode) to `send`, in order; stops at the first error, which names the
/// line or row. Blocking: run it on a blocking thread.
fn read_parts(
    path: &Path,
    format: Format,
    mapping: &Mapping,
    columns: &[Column],
    dims: (usize, usize),
    assembly: &Assembly,
    send: &mut dyn FnMut(Message) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    let mut assembler = Assembler {
        dataset: &assembly.dataset,
        dataset_id: &assembly.dataset_id,
        label: assembly.label.as_deref(),
        max_transitions: assembly.max_transitions.max(1),
        max_body: assembly.max_body_bytes.saturating_sub(16 * 1024).max(1024),
        send,
        seen: HashSet::new(),
        episode: None,
        ordinal: 0,
        previous: None,
        buffer: Vec::new(),
        bytes: 0,
        rows: 0,
        first_step: 0,
        parts: 0,
        length: 0,
    };
    table::for_each_row(path, format, &mapping.wanted(), |cells| {
        let row = mapping.read(columns, cells, dims)?;
        assembler.row(row)
    })?;
    assembler.end_episode()
}

/// A file to read and how its rows become trajectories: what [`drive`] reads.
#[derive(Debug, Clone)]
pub struct Reading {
    /// The file.
    pub path: PathBuf,
    /// Its format.
    pub format: Format,
    /// Its columns ([`table::columns`]).
    pub columns: Vec<Column>,
    /// Which of them the state, action, … are ([`mapping::resolve`]).
    pub mapping: Mapping,
    /// The state's and the action's dimensions.
    pub dims: (usize, usize),
    /// The dataset and the limits of one trajectory.
    pub assembly: Assembly,
}

/// What storing one trajectory gave: its id, its transitions, and whether it was stored before
/// (replayed, nothing stored now).
#[derive(Debug, Clone, Copy)]
pub struct Stored {
    /// The trajectory.
    pub id: i64,
    /// Its transitions.
    pub transitions: usize,
    /// Whether it was found stored.
    pub replayed: bool,
}

/// What [`drive`] says as it goes, for a progress bar.
#[derive(Debug)]
pub enum Progress<'a> {
    /// A trajectory was stored, from `rows` rows of the file; the report so far.
    Stored {
        /// Rows of the file it consumed.
        rows: u64,
        /// The import so far.
        report: &'a ImportReport,
    },
    /// An episode was split (its value, its transitions, its parts).
    Split(&'a str, usize, usize),
}

/// Why [`drive`] stopped before the end of the file.
#[derive(Debug)]
pub enum Stopped<E> {
    /// Storing a trajectory failed with `error`: `stop` says which, and what was stored before.
    Storing {
        /// Where, and what was stored before.
        stop: ImportStop,
        /// The store's error.
        error: E,
    },
    /// A row could not be read (`error` names its line or row); `stop` says what was stored
    /// before.
    Reading {
        /// What was stored before (`episode` and `first_step` are `None`).
        stop: ImportStop,
        /// What is wrong with the file.
        error: anyhow::Error,
    },
    /// The reader itself failed (it panicked): the file may be damaged.
    Reader(String),
}

/// Runs an import: reads the file on a blocking thread (at most two trajectories ahead of the
/// store) and hands each trajectory to `store`, in the file's order, counting what was stored
/// into the report and telling `progress`; stops at the first failure, saying where.
pub async fn drive<E, F, Fut>(
    reading: Reading,
    mut store: F,
    mut progress: impl FnMut(Progress<'_>),
) -> Result<ImportReport, Stopped<E>>
where
    F: FnMut(Part) -> Fut,
    Fut: Future<Output = Result<Stored, E>>,
{
    let (tx, mut rx) = tokio::sync::mpsc::channel::<Message>(2);
    let reader = tokio::task::spawn_blocking(move || -> anyhow::Result<()> {
        let Reading {
            path,
            format,
            columns,
            mapping,
            dims,
            assembly,
        } = reading;
        let mut send = |m: Message| {
            tx.blocking_send(m)
                .map_err(|_| anyhow::anyhow!("the import stopped"))
        };
        read_parts(
            &path, format, &mapping, &columns, dims, &assembly, &mut send,
        )
    });
    let mut report = ImportReport::default();
    let mut failure = None;
    while let Some(message) = rx.recv().await {
        match message {
            Message::Part(part) => {
                let (episode, first_step, rows) =
                    (part.source.episode, part.source.first_step, part.rows);
                match store(part).await {
                    Ok(stored) => {
                        report.stored(stored.id, first_step, stored.transitions, stored.replayed);
                        progress(Progress::Stored {
                            rows,
                            report: &report,
                        });
                    }
                    Err(error) => {
                        failure = Some(Stopped::Storing {
                            stop: ImportStop {
                                episode: Some(episode.unwrap_or_default()),
                                first_step: Some(first_step.unwrap_or_default()),
                                stored_before: std::mem::take(&mut report),
                            },
                            error,
                        });
                        break;
                    }
                }
            }
            Message::Split(episode, length, parts) => {
                report.split_episodes += 1;
                progress(Progress::Split(&episode, length, parts));
            }
            Message::Skipped => report.skipped_episodes += 1,
        }
    }
    // The reader stops at its next part when nobody receives it any more.
    drop(rx);
    let read = reader.await;
    if let Some(stopped) = failure {
        return Err(stopped);
    }
    match read {
        Ok(Ok(())) => Ok(report),
        Ok(Err(error)) => Err(Stopped::Reading {
            stop: ImportStop {
                episode: None,
                first_step: None,
                stored_before: report,
            },
            error,
        }),
        Err(panicked) => Err(Stopped::Reader(panicked.to_string())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_keep_plain_episode_values_and_hash_the_others() {
        assert_eq!(key_part("12"), "12");
        assert_eq!(key_part("run_3.b-x"), "run_3.b-x");
        let hashed = key_part("episode 3/with spaces");
        assert!(hashed.starts_with('h') && hashed.len() == 17, "{hashed}");
        assert_ne!(hashed, key_part("episode 3/with spaces "));
        assert_eq!(episode_of(Some(&Cell::Number(7.0)), 2), ("7".into(), 7));
        assert_eq!(episode_of(Some(&Cell::Number(-1.0)), 2), ("-1".into(), 2));
        assert_eq!(
            episode_of(Some(&Cell::Text("a".into())), 4),
            ("a".into(), 4)
        );
        assert_eq!(episode_of(None, 0), ("0".into(), 0));
    }

    #[test]
    fn a_report_counts_every_trajectory_and_lists_a_bounded_number() {
        let mut report = ImportReport::default();
        for id in 0..MAX_REPORTED_IDS as i64 + 5 {
            report.stored(id, Some(0), 2, id % 2 == 0);
        }
        assert_eq!(report.trajectories, MAX_REPORTED_IDS + 5);
        assert_eq!(report.transitions, 2 * (MAX_REPORTED_IDS + 5));
        assert_eq!(report.trajectory_ids.len(), MAX_REPORTED_IDS);
        assert_eq!(report.trajectory_ids[..3], [0, 1, 2]);
        // Another file's report adds its counts, and its ids while there is room.
        let mut first = ImportReport::default();
        first.stored(7, Some(0), 1, false);
        first.add(&report);
        assert_eq!(first.trajectories, MAX_REPORTED_IDS + 6);
        assert_eq!(first.trajectory_ids.len(), MAX_REPORTED_IDS);
        assert_eq!(first.trajectory_ids[..2], [7, 0]);
    }
}
