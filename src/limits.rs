//! The ranges of everything a client can set, documented once and used by every layer that
//! checks them (the experiment settings at the door, the planner and the GP behind it).
//!
//! Each upper bound keeps one request's worst case bounded: a proposal costs at most
//! `MAX_CANDIDATES × MAX_EXTENSIONS` extensions, a fit at most `1 + MAX_RESTARTS` optimiser
//! starts, a precondition query at most `MAX_POINTS` GP predictions.

/// Candidate trajectories (RRT runs) per proposal: `1 ..= 200`.
pub const MAX_CANDIDATES: u32 = 200;
/// RRT extension budget of one search: `1 ..= 200 000`.
pub const MAX_EXTENSIONS: u32 = 200_000;
/// Trajectories per learning iteration: `1 ..= 10 000`.
pub const MAX_BATCH_SIZE: u32 = 10_000;
/// Planned learning iterations `J` of the β schedule: `1 ..= 100 000`.
pub const MAX_ITERATIONS: u32 = 100_000;
/// Extra seeded hyperparameter-optimiser starts: `0 ..= 20`.
pub const MAX_RESTARTS: usize = 20;
/// Seconds an open proposal stays leased: `1 ..= 604 800` (a week).
pub const MAX_PROPOSAL_TTL_SECONDS: u32 = 7 * 24 * 3600;
/// Characters of an experiment's name: `0 ..= 200`.
pub const MAX_NAME_LEN: usize = 200;
/// Characters of a proposal's `client_id`: `1 ..= 200`.
pub const MAX_CLIENT_ID_LEN: usize = 200;
/// Characters of an `Idempotency-Key`: `1 ..= 200` visible ASCII.
pub const MAX_IDEMPOTENCY_KEY_LEN: usize = 200;
/// Characters of a trajectory's `source.dataset` (`1 ..=`) and `source.label` (`0 ..=`): `1000`.
pub const MAX_SOURCE_TEXT_LEN: usize = 1000;
/// Transitions in one posted trajectory: `1 ..= 10 000`.
pub const MAX_TRANSITIONS: usize = 10_000;
/// Points in one precondition query: `1 ..= 100 000`.
pub const MAX_POINTS: usize = 100_000;
/// Transitions in one JSON page: `1 ..= 1000`, default [`DEFAULT_PAGE`].
pub const MAX_PAGE: i64 = 1000;
/// Transitions in a JSON page when the client does not say.
pub const DEFAULT_PAGE: i64 = 100;
/// Rows of one explicit CSV page (a CSV export is unlimited by default).
pub const MAX_CSV_ROWS: i64 = 1_000_000_000;
/// Candidate trajectories a client may post with one proposal or plan: `1 ..= 200`; their
/// steps together count against [`MAX_POINTS`].
pub const MAX_CLIENT_CANDIDATES: usize = 200;
/// Points along one side of a precondition map: `2 ..= 200`, default [`DEFAULT_MAP_SIDE`]. A
/// map costs at most `MAX_MAP_SIDE²` GP predictions, less than one [`MAX_POINTS`] query.
pub const MAX_MAP_SIDE: usize = 200;
/// Points along one side of a precondition map when the client does not say.
pub const DEFAULT_MAP_SIDE: usize = 41;
/// Training points a precondition map carries for drawing (evenly spread over the training set).
pub const MAX_MAP_TRAINING_POINTS: usize = 2000;
/// Rows of each list of an experiment's timeline (iterations, model versions): the first
/// `10 000`.
pub const MAX_TIMELINE_ROWS: i64 = 10_000;
/// Transitions after a model version's training set that its diagnostics judge (the first
/// `10 000`).
pub const MAX_LATER_TRANSITIONS: i64 = 10_000;
