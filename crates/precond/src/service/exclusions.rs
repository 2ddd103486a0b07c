//! Data hygiene: leave a bad run or a bad calibration day out of an experiment's model, and
//! bring it back. Making or restoring an exclusion requests a forced refit in the same
//! transaction ([`Store::create_exclusion`](crate::store::Store::create_exclusion)); until that
//! refit is swapped in, the version answering still holds what it was fitted on, and an
//! exclusion says so (`applied`).

use super::experiments::{check_page, next_offset};
use super::{Error, Result, Service};
use crate::api::ExclusionRequest;
use crate::limits::{DEFAULT_PAGE, MAX_SOURCE_TEXT_LEN, text_problem};
use crate::mde::ServedModel;
use crate::store::{Exclusion, ExclusionOutcome, ExclusionScope, RestoreOutcome, timestamp};
use time::OffsetDateTime;
use time::format_description::well_known::Rfc3339;

/// An exclusion and whether the model answering now agrees with it.
#[derive(Debug, Clone)]
pub struct ExclusionRecord {
    /// As stored.
    pub exclusion: Exclusion,
    /// Whether the version answering was fitted under it as it stands (in effect: fitted
    /// without its trajectories; restored: not fitted under it).
    pub applied: bool,
}

/// A page of exclusions, newest first.
#[derive(Debug, Clone)]
pub struct Exclusions {
    /// The page.
    pub items: Vec<ExclusionRecord>,
    /// Exclusions in all.
    pub total: i64,
    /// The next page's offset, if any.
    pub next: Option<i64>,
}

fn record(exclusion: Exclusion, model: &ServedModel) -> ExclusionRecord {
    let fitted_under = model
        .fit
        .as_ref()
        .is_some_and(|f| f.exclusions.contains(&exclusion.id));
    let in_effect = exclusion.restored_at.is_none();
    ExclusionRecord {
        applied: fitted_under == in_effect,
        exclusion,
    }
}

/// An RFC 3339 instant of `field`, in the store's own format (so that it compares with stored
/// times).
fn instant(field: &str, text: &str) -> Result<(OffsetDateTime, String)> {
    let t = OffsetDateTime::parse(text, &Rfc3339).map_err(|e| {
        Error::validation(
            field,
            format!("{text:?} is not an RFC 3339 time (e.g. 2026-11-29T08:00:00Z): {e}"),
        )
    })?;
    Ok((t, timestamp(t)))
}

/// What `request` names, checked.
fn scope_of(request: &ExclusionRequest) -> Result<ExclusionScope> {
    let reason = &request.reason;
    let n = reason.chars().count();
    if n == 0 || n > MAX_SOURCE_TEXT_LEN {
        return Err(Error::validation(
            "reason",
            format!("must be 1 to {MAX_SOURCE_TEXT_LEN} characters, got {n}"),
        ));
    }
    if let Some(problem) = text_problem(reason) {
        return Err(Error::validation("reason", problem));
    }
    match (request.trajectory_id, &request.since, &request.until) {
        (Some(t), None, None) => {
            if t < 1 {
                return Err(Error::validation(
                    "trajectory_id",
                    format!("must be at least 1, got {t}"),
                ));
            }
            Ok(ExclusionScope::Trajectory(t))
        }
        (None, Some(from), Some(to)) => {
            let (from_t, from) = instant("since", from)?;
            let (to_t, to) = instant("until", to)?;
            if to_t <= from_t {
                return Err(Error::validation(
                    "until",
                    format!("must be after `since` ({from}), got {to}"),
                ));
            }
            Ok(ExclusionScope::TimeRange { from, to })
        }
        (Some(_), _, _) => Err(Error::validation(
            "trajectory_id",
            "give `trajectory_id` or a time range (`since` and `until`), not both",
        )),
        (None, Some(_), None) => Err(Error::validation(
            "until",
            "a time range needs `until` (exclusive) beside `since`",
        )),
        (None, None, Some(_)) => Err(Error::validation(
            "since",
            "a time range needs `since` (inclusive) beside `until`",
        )),
        (None, None, None) => Err(Error::validation(
            "trajectory_id",
            "give the trajectory to leave out, or a time range (`since` and `until`)",
        )),
    }
}

impl Service {
    /// Leaves what `request` names out of experiment `id`'s model, recorded as made by `by`
    /// (the caller's token fingerprint), and wakes a fit worker for the refit it requested.
    pub async fn exclude(
        &self,
        id: i64,
        request: &ExclusionRequest,
        by: Option<&str>,
    ) -> Result<ExclusionRecord> {
        let scope = scope_of(request)?;
        let live = self.live(id).await?;
        let outcome = self
            .store
            .create_exclusion(id, &scope, &request.reason, by)
            .await?;
        match outcome {
            ExclusionOutcome::Created(exclusion) => {
                tracing::info!(
                    experiment = id,
                    exclusion = exclusion.id,
                    trajectories = exclusion.trajectory_ids.len(),
                    transitions = exclusion.n_transitions,
                    "trajectories excluded from the model; refit requested"
                );
                self.fits.wake();
                Ok(record(exclusion, &live.model()))
            }
            ExclusionOutcome::NoSuchTrajectory => Err(Error::validation(
                "trajectory_id",
                format!(
                    "no trajectory {} in experiment {id}",
                    request.trajectory_id.unwrap_or_default()
                ),
            )),
            ExclusionOutcome::CoversNothing => Err(Error::validation(
                "since",
                format!("no trajectory of experiment {id} was stored in this time range"),
            )),
            ExclusionOutcome::LeavesNothing { n_transitions } => Err(Error::Conflict(format!(
                "with this exclusion none of the experiment's {n_transitions} transitions \
                 would be left to fit; restore another exclusion first"
            ))),
        }
    }

    /// Restores exclusion `exclusion_id` of experiment `id` (recorded as done by `by`): the
    /// next fit, requested here, takes its trajectories in again. Restoring one restored
    /// before changes nothing and answers it as it stands.
    pub async fn restore_exclusion(
        &self,
        id: i64,
        exclusion_id: i64,
        by: Option<&str>,
    ) -> Result<ExclusionRecord> {
        let live = self.live(id).await?;
        match self.store.restore_exclusion(id, exclusion_id, by).await? {
            RestoreOutcome::Restored(exclusion) => {
                tracing::info!(
                    experiment = id,
                    exclusion = exclusion_id,
                    "exclusion restored; refit requested"
                );
                self.fits.wake();
                Ok(record(exclusion, &live.model()))
            }
            RestoreOutcome::AlreadyRestored(exclusion) => Ok(record(exclusion, &live.model())),
            RestoreOutcome::NotFound => Err(Error::NotFound(format!(
                "no exclusion {exclusion_id} in experiment {id}"
            ))),
        }
    }

    /// A page of experiment `id`'s exclusions, newest first (default page size 100).
    pub async fn exclusions(&self, id: i64, offset: i64, limit: Option<i64>) -> Result<Exclusions> {
        check_page(offset, limit)?;
        let live = self.live(id).await?;
        let model = live.model();
        let (items, total) = self
            .store
            .exclusions(id, offset, limit.unwrap_or(DEFAULT_PAGE))
            .await?;
        let next = next_offset(offset, items.len(), total);
        Ok(Exclusions {
            items: items.into_iter().map(|e| record(e, &model)).collect(),
            total,
            next,
        })
    }
}
