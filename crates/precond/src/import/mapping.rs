//! Which columns of a table are the state, the action, the next state and the episode: given
//! by the user, or found by the usual conventions.
//!
//! - precond's own CSV export and most logs: `s.<name>`/`s_<name>` (state), `a.<name>`/
//!   `a_<name>` (action), `s_next.<name>`/`s_next_<name>` (next state); `s_pred…` is read only
//!   when the experiment's model is the client's;
//! - LeRobot: `observation.state` and `action` (list columns, or scalar columns
//!   `observation.state.0`, … / `action_0`, …), and no next state: it is the next frame's
//!   state within the episode;
//! - episodes: the first of `episode_index`, `episode`, `episode_id`, `trajectory_id`.
//!
//! Scalar columns whose suffixes are the space's component names are put in the space's order;
//! numbered ones in numeric order; others stay in file order.

use super::table::{Cell, Column};
use anyhow::{Context, bail};

/// How one vector of a row is read: scalar columns, or one list column.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Vector {
    /// One component per column, in order (indices into the table's columns).
    Columns(Vec<usize>),
    /// One list column holding every component.
    List(usize),
}

impl Vector {
    /// The columns it reads.
    pub fn columns(&self) -> Vec<usize> {
        match self {
            Self::Columns(c) => c.clone(),
            Self::List(i) => vec![*i],
        }
    }

    /// Its column names, for people.
    pub fn describe(&self, columns: &[Column]) -> String {
        match self {
            Self::Columns(c) => c
                .iter()
                .map(|&i| columns[i].name.as_str())
                .collect::<Vec<_>>()
                .join(", "),
            Self::List(i) => format!("{} (list)", columns[*i].name),
        }
    }
}

/// The roles of a table's columns.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Mapping {
    /// The state `s`.
    pub state: Vector,
    /// The action `a`.
    pub action: Vector,
    /// The next state `s_next`; `None`: the next row's state within the episode.
    pub next_state: Option<Vector>,
    /// The client's prediction `s_pred` (experiments whose model is the client's).
    pub predicted: Option<Vector>,
    /// The episode column; `None`: the whole file is one episode.
    pub episode: Option<usize>,
}

impl Mapping {
    /// Every column the mapping reads, each once, in the order [`Mapping::read`] expects.
    pub fn wanted(&self) -> Vec<usize> {
        let mut out = self.state.columns();
        out.extend(self.action.columns());
        for v in [&self.next_state, &self.predicted].into_iter().flatten() {
            out.extend(v.columns());
        }
        out.extend(self.episode);
        out
    }

    /// For people: which columns play which role.
    pub fn describe(&self, columns: &[Column]) -> String {
        let mut out = format!(
            "state <- {}; action <- {}; next state <- {}",
            self.state.describe(columns),
            self.action.describe(columns),
            self.next_state
                .as_ref()
                .map_or("the next row's state in the episode".into(), |v| v
                    .describe(columns)),
        );
        if let Some(p) = &self.predicted {
            out += &format!("; prediction <- {}", p.describe(columns));
        }
        out += &match self.episode {
            Some(e) => format!("; episodes by {}", columns[e].name),
            None => "; one episode per file".into(),
        };
        out
    }
}

/// What the user said about the columns (`None`: find it).
#[derive(Debug, Clone, Default)]
pub struct Given {
    /// How mistakes name what was given: the command line's flags (`--next-state`, `false`)
    /// or the import route's query parameters (`next_state`, `true`).
    pub as_query: bool,
    /// `--state`.
    pub state: Option<Vec<String>>,
    /// `--action`.
    pub action: Option<Vec<String>>,
    /// `--next-state`.
    pub next_state: Option<Vec<String>>,
    /// `--predicted-state`.
    pub predicted: Option<Vec<String>>,
    /// `--episode` (`none`: one episode per file).
    pub episode: Option<String>,
}

/// The experiment's spaces as the mapping needs them.
#[derive(Debug, Clone)]
pub struct Spaces {
    /// State component names.
    pub state: Vec<String>,
    /// Action component names.
    pub action: Vec<String>,
    /// Whether every transition needs the client's prediction (`model.kind` `client`).
    pub client_side: bool,
}

impl Given {
    /// What the user calls the option named `name` (`next-state`): `--next-state` on the
    /// command line, `next_state` in a query string.
    pub fn flag(&self, name: &str) -> String {
        if self.as_query {
            name.replace('-', "_")
        } else {
            format!("--{name}")
        }
    }
}

const EPISODE_COLUMNS: [&str; 4] = ["episode_index", "episode", "episode_id", "trajectory_id"];

fn index(columns: &[Column], name: &str, flag: &str) -> anyhow::Result<usize> {
    columns
        .iter()
        .position(|c| c.name == name)
        .with_context(|| {
            format!(
                "{flag}: no column {name:?} (the file has {})",
                names(columns)
            )
        })
}

/// The file's column names for a message: the first 20, and how many more (a header of
/// 10^5 columns must not make a 600 KB answer).
fn names(columns: &[Column]) -> String {
    const SHOWN: usize = 20;
    let mut out = columns
        .iter()
        .take(SHOWN)
        .map(|c| c.name.as_str())
        .collect::<Vec<_>>()
        .join(", ");
    if columns.len() > SHOWN {
        out += &format!(" and {} more", columns.len() - SHOWN);
    }
    out
}

/// The vector the user named: one list column, or scalar columns.
fn given_vector(
    columns: &[Column],
    given: &[String],
    dim: usize,
    flag: &str,
) -> anyhow::Result<Vector> {
    if let [one] = given
        && let Ok(i) = index(columns, one, flag)
        && columns[i].list
    {
        return Ok(Vector::List(i));
    }
    let idx = given
        .iter()
        .map(|n| {
            let i = index(columns, n, flag)?;
            if columns[i].list {
                bail!("{flag}: {n:?} is a list column; name it alone");
            }
            Ok(i)
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    check_dim(&Vector::Columns(idx.clone()), columns, dim, flag)?;
    Ok(Vector::Columns(idx))
}

fn check_dim(v: &Vector, columns: &[Column], dim: usize, flag: &str) -> anyhow::Result<()> {
    if let Vector::Columns(c) = v
        && c.len() != dim
    {
        bail!(
            "{flag}: {} columns ({}) for the experiment's {dim} components",
            c.len(),
            v.describe(columns)
        );
    }
    Ok(())
}

/// Scalar columns named `<prefix><suffix>` for one of `prefixes`, ordered by the space's
/// names when the suffixes are exactly those, numerically when they are numbers, else in file
/// order; or the list column named exactly like a prefix without its separator.
fn by_prefix(
    columns: &[Column],
    prefixes: &[&str],
    exclude: &[&str],
    names: &[String],
) -> Option<Vector> {
    for p in prefixes {
        let bare = p.trim_end_matches(['.', '_']);
        if let Some(i) = columns.iter().position(|c| c.list && c.name == bare) {
            return Some(Vector::List(i));
        }
    }
    for p in prefixes {
        let found: Vec<(usize, &str)> = columns
            .iter()
            .enumerate()
            .filter(|(_, c)| !c.list && !exclude.iter().any(|x| c.name.starts_with(x)))
            .filter_map(|(i, c)| c.name.strip_prefix(p).map(|suffix| (i, suffix)))
            .filter(|(_, suffix)| !suffix.is_empty())
            .collect();
        if found.is_empty() {
            continue;
        }
        let mut sorted = found.clone();
        let suffixes: Vec<&str> = found.iter().map(|(_, s)| *s).collect();
        if suffixes.len() == names.len() && names.iter().all(|n| suffixes.contains(&n.as_str())) {
            sorted.sort_by_key(|(_, s)| names.iter().position(|n| n == s));
        } else if suffixes.iter().all(|s| s.parse::<u64>().is_ok()) {
            sorted.sort_by_key(|(_, s)| s.parse::<u64>().unwrap_or(u64::MAX));
        }
        return Some(Vector::Columns(
            sorted.into_iter().map(|(i, _)| i).collect(),
        ));
    }
    None
}

/// Finds the mapping of a table's columns (see the module docs); the error names what is
/// missing and what the file has.
pub fn resolve(columns: &[Column], spaces: &Spaces, given: &Given) -> anyhow::Result<Mapping> {
    let (n, m) = (spaces.state.len(), spaces.action.len());
    let own = |v: Option<Vector>, dim: usize, flag: &str| -> anyhow::Result<Option<Vector>> {
        if let Some(v) = &v {
            check_dim(v, columns, dim, flag)?;
        }
        Ok(v)
    };
    let state = match &given.state {
        Some(g) => given_vector(columns, g, n, &given.flag("state"))?,
        None => own(
            by_prefix(columns, &["s.", "s_"], &["s_next", "s_pred"], &spaces.state).or_else(|| {
                by_prefix(
                    columns,
                    &["observation.state.", "observation.state_"],
                    &[],
                    &spaces.state,
                )
            }),
            n,
            "the state columns",
        )?
        .with_context(|| {
            format!(
                "no state columns found (s.<name>, s_<name> or observation.state; the file has {}): \
                 name them with {}",
                names(columns),
                given.flag("state")
            )
        })?,
    };
    let action = match &given.action {
        Some(g) => given_vector(columns, g, m, &given.flag("action"))?,
        None => own(
            by_prefix(columns, &["a.", "a_"], &[], &spaces.action)
                .or_else(|| by_prefix(columns, &["action.", "action_"], &[], &spaces.action)),
            m,
            "the action columns",
        )?
        .with_context(|| {
            format!(
                "no action columns found (a.<name>, a_<name> or action; the file has {}): name \
                 them with {}",
                names(columns),
                given.flag("action")
            )
        })?,
    };
    let next_state = match &given.next_state {
        Some(g) => Some(given_vector(columns, g, n, &given.flag("next-state"))?),
        None => own(
            by_prefix(columns, &["s_next.", "s_next_"], &[], &spaces.state)
                .or_else(|| by_prefix(columns, &["next.observation.state."], &[], &spaces.state)),
            n,
            "the next-state columns",
        )?,
    };
    let predicted = match (&given.predicted, spaces.client_side) {
        (Some(g), true) => Some(given_vector(columns, g, n, &given.flag("predicted-state"))?),
        (Some(_), false) => bail!(
            "{}: the experiment's model is not the client's; the service predicts with it",
            given.flag("predicted-state")
        ),
        (None, true) => Some(
            own(
                by_prefix(columns, &["s_pred.", "s_pred_"], &[], &spaces.state),
                n,
                "the predicted-state columns",
            )?
            .with_context(|| {
                format!(
                    "the experiment's model is the client's: every transition needs its \
                     prediction (s_pred.<name> columns, or {})",
                    given.flag("predicted-state")
                )
            })?,
        ),
        (None, false) => None,
    };
    let episode = match given.episode.as_deref() {
        Some("none") => None,
        Some(name) => Some(index(columns, name, &given.flag("episode"))?),
        None => EPISODE_COLUMNS
            .iter()
            .find_map(|e| columns.iter().position(|c| c.name == *e)),
    };
    if let Some(e) = episode
        && columns[e].list
    {
        bail!("the episode column {:?} is a list", columns[e].name);
    }
    let mapping = Mapping {
        state,
        action,
        next_state,
        predicted,
        episode,
    };
    let wanted = mapping.wanted();
    for (k, i) in wanted.iter().enumerate() {
        if wanted[..k].contains(i) {
            bail!(
                "the column {:?} is given two roles ({})",
                columns[*i].name,
                mapping.describe(columns)
            );
        }
    }
    Ok(mapping)
}

/// One row's values, read by a mapping from the cells at [`Mapping::wanted`].
#[derive(Debug, Clone, PartialEq)]
pub struct RowValues {
    /// State.
    pub s: Vec<f64>,
    /// Action.
    pub a: Vec<f64>,
    /// Next state, when the table has it.
    pub s_next: Option<Vec<f64>>,
    /// The client's prediction, when read.
    pub s_pred: Option<Vec<f64>>,
    /// The episode's value, when the table has an episode column.
    pub episode: Option<Cell>,
}

impl Mapping {
    /// The values of one row from its cells at [`Mapping::wanted`]; the error names the column
    /// and what it held.
    pub fn read(
        &self,
        columns: &[Column],
        cells: Vec<Cell>,
        dims: (usize, usize),
    ) -> anyhow::Result<RowValues> {
        let mut cells = cells.into_iter();
        let mut take = |v: &Vector, dim: usize| -> anyhow::Result<Vec<f64>> {
            let out = match v {
                Vector::List(i) => match cells.next() {
                    Some(Cell::List(xs)) => {
                        if xs.len() != dim {
                            bail!(
                                "{}: {} numbers for the experiment's {dim} components",
                                columns[*i].name,
                                xs.len()
                            );
                        }
                        xs
                    }
                    other => bail!(
                        "{}: expected a list of numbers, got {}",
                        columns[*i].name,
                        other.map_or("nothing".into(), |c| c.describe())
                    ),
                },
                Vector::Columns(idx) => idx
                    .iter()
                    .map(|i| match cells.next() {
                        Some(Cell::Number(x)) => Ok(x),
                        other => bail!(
                            "{}: expected a number, got {}",
                            columns[*i].name,
                            other.map_or("nothing".into(), |c| c.describe())
                        ),
                    })
                    .collect::<anyhow::Result<_>>()?,
            };
            if let Some(k) = out.iter().position(|x| !x.is_finite()) {
                let name = match v {
                    Vector::List(i) => format!("{}[{k}]", columns[*i].name),
                    Vector::Columns(idx) => columns[idx[k]].name.clone(),
                };
                bail!("{name}: {} is not a finite number", out[k]);
            }
            Ok(out)
        };
        let s = take(&self.state, dims.0)?;
        let a = take(&self.action, dims.1)?;
        let s_next = self
            .next_state
            .as_ref()
            .map(|v| take(v, dims.0))
            .transpose()?;
        let s_pred = self
            .predicted
            .as_ref()
            .map(|v| take(v, dims.0))
            .transpose()?;
        let episode = match self.episode {
            Some(i) => match cells.next() {
                Some(Cell::Missing) | None => {
                    bail!("{}: no episode value", columns[i].name)
                }
                Some(c) => Some(c),
            },
            None => None,
        };
        Ok(RowValues {
            s,
            a,
            s_next,
            s_pred,
            episode,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cols(names: &[&str]) -> Vec<Column> {
        names
            .iter()
            .map(|n| Column {
                name: n.trim_end_matches("[]").to_string(),
                list: n.ends_with("[]"),
            })
            .collect()
    }

    fn spaces() -> Spaces {
        Spaces {
            state: vec!["x".into(), "y".into()],
            action: vec!["dx".into(), "dy".into()],
            client_side: false,
        }
    }

    #[test]
    fn precond_exports_are_read_by_name_in_the_spaces_order() {
        let c = cols(&[
            "id",
            "trajectory_id",
            "step",
            "s.y",
            "s.x",
            "a.dx",
            "a.dy",
            "s_next.x",
            "s_next.y",
            "s_pred.x",
            "s_pred.y",
            "deviation",
        ]);
        let m = resolve(&c, &spaces(), &Given::default()).unwrap();
        assert_eq!(m.state, Vector::Columns(vec![4, 3]));
        assert_eq!(m.action, Vector::Columns(vec![5, 6]));
        assert_eq!(m.next_state, Some(Vector::Columns(vec![7, 8])));
        assert_eq!((m.predicted, m.episode), (None, Some(1)));
    }

    #[test]
    fn lerobot_lists_have_no_next_state_and_episodes_by_index() {
        let c = cols(&[
            "observation.state[]",
            "action[]",
            "timestamp",
            "frame_index",
            "episode_index",
        ]);
        let m = resolve(&c, &spaces(), &Given::default()).unwrap();
        assert_eq!((m.state, m.action), (Vector::List(0), Vector::List(1)));
        assert_eq!((m.next_state, m.episode), (None, Some(4)));
        let numbered = cols(&[
            "action_1",
            "action_0",
            "observation.state.1",
            "observation.state.0",
        ]);
        let m = resolve(&numbered, &spaces(), &Given::default()).unwrap();
        assert_eq!(m.state, Vector::Columns(vec![3, 2]));
        assert_eq!(m.action, Vector::Columns(vec![1, 0]));
        assert_eq!(m.episode, None);
    }

    #[test]
    fn a_wide_header_is_named_in_part() {
        let wide: Vec<String> = (0..100_000).map(|i| format!("c{i}")).collect();
        let refs: Vec<&str> = wide.iter().map(String::as_str).collect();
        let e = resolve(&cols(&refs), &spaces(), &Given::default())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("c0, c1") && e.contains("c19 and 99980 more"),
            "{e}"
        );
        assert!(e.len() < 1000, "{} bytes", e.len());
    }

    #[test]
    fn mistakes_name_the_flag_and_what_the_file_has() {
        let c = cols(&["s_x", "s_y", "s_z", "a_dx", "a_dy"]);
        let e = resolve(&c, &spaces(), &Given::default())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("3 columns (s_x, s_y, s_z)") && e.contains("2 components"),
            "{e}"
        );
        let e = resolve(&cols(&["px", "py"]), &spaces(), &Given::default())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("no state columns") && e.contains("px, py") && e.contains("--state"),
            "{e}"
        );
        let given = Given {
            state: Some(vec!["s_x".into(), "s_q".into()]),
            ..Given::default()
        };
        let e = resolve(&c, &spaces(), &given).unwrap_err().to_string();
        assert!(e.starts_with("--state: no column \"s_q\""), "{e}");
        let given = Given {
            state: Some(vec!["s_x".into(), "s_y".into()]),
            action: Some(vec!["a_dx".into(), "s_y".into()]),
            ..Given::default()
        };
        let e = resolve(&c, &spaces(), &given).unwrap_err().to_string();
        assert!(e.contains("two roles"), "{e}");
        let client = Spaces {
            client_side: true,
            ..spaces()
        };
        let e = resolve(
            &cols(&["s_x", "s_y", "a_dx", "a_dy"]),
            &client,
            &Given::default(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("prediction"), "{e}");
    }

    #[test]
    fn a_row_is_read_and_checked() {
        let c = cols(&["s_x", "s_y", "a_dx", "a_dy", "episode"]);
        let m = resolve(&c, &spaces(), &Given::default()).unwrap();
        let n = |x: f64| Cell::Number(x);
        let row = m
            .read(
                &c,
                vec![n(1.0), n(2.0), n(0.1), n(0.0), Cell::Text("ep-a".into())],
                (2, 2),
            )
            .unwrap();
        assert_eq!(
            (row.s, row.a, row.s_next),
            (vec![1.0, 2.0], vec![0.1, 0.0], None)
        );
        assert_eq!(row.episode, Some(Cell::Text("ep-a".into())));
        let e = m
            .read(
                &c,
                vec![n(1.0), n(f64::NAN), n(0.1), n(0.0), n(3.0)],
                (2, 2),
            )
            .unwrap_err()
            .to_string();
        assert_eq!(e, "s_y: NaN is not a finite number");
        let e = m
            .read(
                &c,
                vec![n(1.0), Cell::Text("x".into()), n(0.1), n(0.0), n(3.0)],
                (2, 2),
            )
            .unwrap_err()
            .to_string();
        assert_eq!(e, "s_y: expected a number, got \"x\"");
    }
}
