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

/// Fewest inducing points of the sparse GP (`mde.inducing_points`).
pub const MIN_INDUCING_POINTS: usize = 16;

/// Most inducing points of the sparse GP: its fit costs `O(n m²)` and its memory `O(n m)`.
pub const MAX_INDUCING_POINTS: usize = 4096;
/// Fewest transitions per local expert (`mde.expert_size`).
pub const MIN_EXPERT_SIZE: usize = 50;

/// Most transitions per local expert: an expert is an exact GP, `O(n_e³)` to fit.
pub const MAX_EXPERT_SIZE: usize = 3000;
/// Fewest transitions the sparse GP's kernel and label cap are chosen on
/// (`mde.selection_subset`).
pub const MIN_SELECTION_SUBSET: usize = 200;

/// Most transitions the sparse GP's kernel and label cap are chosen on: the choice fits exact
/// GPs, `O(n³)` each, and the exact GP itself is used up to as many
/// ([`crate::mde::AUTO_EXACT_MAX_N`]).
pub const MAX_SELECTION_SUBSET: usize = 3000;
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
/// The server's request body limit by default (`--max-body-bytes`), 4 MiB: `precond import`
/// splits episodes for it by default, as the import route does for the server's own limit, so
/// that both store the same parts under the same keys.
pub const DEFAULT_MAX_BODY_BYTES: usize = 4 * 1024 * 1024;
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
/// Largest magnitude of a number that fixes a domain's geometry: a state or action bound, a
/// discrete action value, an obstacle corner, a goal radius, a distance weight, an entry of a
/// linear model: `1e12`. Within it, the widths of the bounds, squared distances and the MDE's
/// targets stay far from overflowing `f64` (a width of `2e308` is infinite and nothing can be
/// sampled in it).
pub const MAX_MAGNITUDE: f64 = 1e12;
/// Largest magnitude of the MDE's prior mean `mde.prior_mean`: [`MAX_MAGNITUDE`], so that the
/// centred targets' mean square stays finite.
pub const MAX_PRIOR_MEAN: f64 = MAX_MAGNITUDE;
/// Largest value of the β schedule's `k1` and `k2`, the exploration weight `c` and the magnitude
/// of `test_beta`: `1e6`. A β of 8 already asks for a one-in-10¹⁵ error; beyond `1e6` only the
/// arithmetic changes (`2 k1` overflows at `k1 ≈ 9e307`, `μ − c σ` becomes infinite).
pub const MAX_LEARNING_SCALE: f64 = 1e6;

/// Why `text` (a name, a client id) may not be stored as it is: a control character (NUL,
/// ESC, CR, LF, …, which end up in terminals, logs and CSV exports) or a bidirectional
/// formatting character (U+202A–U+202E, U+2066–U+2069, U+200E, U+200F, which make a string
/// display other than it reads); `None` when it is fine. The one rule for free-form labels.
pub fn text_problem(text: &str) -> Option<String> {
    let bidi = |c: char| matches!(c, '\u{200E}' | '\u{200F}' | '\u{202A}'..='\u{202E}' | '\u{2066}'..='\u{2069}');
    text.chars()
        .enumerate()
        .find(|(_, c)| c.is_control() || bidi(*c))
        .map(|(i, c)| {
            format!(
                "must not hold control or bidirectional formatting characters (U+{:04X} at \
                 character {i})",
                c as u32
            )
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels_refuse_control_and_bidi_characters() {
        for ok in ["", "arm 2 — bench ü", "x0", "名前"] {
            assert_eq!(text_problem(ok), None, "{ok:?}");
        }
        for (bad, at) in [
            ("a\u{0}b", "U+0000 at character 1"),
            ("\u{1b}[2J", "U+001B at character 0"),
            ("line\nbreak", "U+000A"),
            ("x\u{7f}", "U+007F"),
            ("abc\u{202e}gpj.exe", "U+202E at character 3"),
            ("\u{2066}", "U+2066"),
        ] {
            let why = text_problem(bad).unwrap_or_default();
            assert!(why.contains(at), "{bad:?}: {why}");
        }
    }
}
