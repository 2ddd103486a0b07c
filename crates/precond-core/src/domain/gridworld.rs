//! The icy gridworld (the paper's first scenario, after Vemula et al. 2020): its model and
//! planning helpers. The true dynamics (ice reverses x-moves, obstacles block) live in
//! `crate::sim::gridworld`.

use super::{
    BOUND_TOLERANCE, Domain, DomainError, DynamicsModel, FeatureMap, LocalModel, Problem, Space,
    euclidean,
};
use rand::{Rng, RngCore};
use serde::{Deserialize, Serialize};

/// The default layout: 12×12, an obstacle wall across row 6 with a two-cell gap at x = 5..6,
/// and two bands of ice (rows 2–3 at x = 2..9, row 9 at x = 1..10).
///
/// String `y` is the row at `y`; its character `x` is the cell `[x, y]`. `.` is free, `#` an
/// obstacle, `~` ice (on ice the x-moves `[±1, 0]` are reversed).
pub const DEFAULT_MAP: [&str; 12] = [
    "............",
    "............",
    "..~~~~~~~~..",
    "..~~~~~~~~..",
    "............",
    "............",
    "#####..#####",
    "............",
    "............",
    ".~~~~~~~~~~.",
    "............",
    "............",
];

/// A cell of the grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Cell {
    /// `.`: the robot moves as commanded.
    Free,
    /// `#`: a move into it leaves the robot where it was.
    Obstacle,
    /// `~`: the x-moves are reversed.
    Ice,
}

/// How a gridworld state-action is fed to the MDE.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
#[serde(rename_all = "snake_case")]
pub enum GridFeatures {
    /// `(x, y, dx, dy)` scaled to the unit box: one set of length scales for every move (the
    /// paper's).
    #[default]
    Scaled,
    /// `(x, y)` of each move in its own pair of coordinates (zero for the other moves), then the
    /// move one-hot: each move gets its own length scales, so how far what is learned about one
    /// move spreads is not limited by how sharply another move's deviation changes.
    PerMove,
}

/// The icy gridworld domain. States are `[x, y]` cells, actions the four unit moves.
#[derive(Debug, Clone)]
pub struct IcyGridworld {
    feature_map: GridFeatures,
    width: usize,
    height: usize,
    cells: Vec<Cell>,
    map: Vec<String>,
    state_space: Space,
    action_space: Space,
    rollout_length: usize,
}

/// The four moves, in the order the action space lists them.
pub const MOVES: [[f64; 2]; 4] = [[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]];

impl IcyGridworld {
    /// Largest accepted side of a map.
    pub const MAX_SIDE: usize = 256;

    /// Parses a map of characters (see [`DEFAULT_MAP`]).
    pub fn new<S: AsRef<str>>(map: &[S]) -> Result<Self, DomainError> {
        let height = map.len();
        if height == 0 {
            return Err(DomainError::at("map", "the map has no rows"));
        }
        let width = map[0].as_ref().chars().count();
        if width == 0 || width > Self::MAX_SIDE || height > Self::MAX_SIDE {
            return Err(DomainError::at(
                "map",
                format!(
                    "the map must be between 1 and {} cells on each side, got {width}×{height}",
                    Self::MAX_SIDE
                ),
            ));
        }
        let mut cells = Vec::with_capacity(width * height);
        for (y, row) in map.iter().enumerate() {
            let row = row.as_ref();
            if row.chars().count() != width {
                return Err(DomainError::at(
                    "map",
                    format!(
                        "row {y} has {} cells, row 0 has {width}: every row must be equally long",
                        row.chars().count()
                    ),
                ));
            }
            for (x, ch) in row.chars().enumerate() {
                cells.push(match ch {
                    '.' => Cell::Free,
                    '#' => Cell::Obstacle,
                    '~' => Cell::Ice,
                    other => {
                        return Err(DomainError::at("map", format!(
                            "cell [{x}, {y}] is {other:?}; use '.' (free), '#' (obstacle) or '~' (ice)"
                        )));
                    }
                });
            }
        }
        if cells.iter().filter(|c| **c != Cell::Obstacle).count() < 2 {
            return Err(DomainError::at(
                "map",
                "the map needs at least two cells that are not obstacles",
            ));
        }
        let state_space = Space {
            names: vec!["x".into(), "y".into()],
            low: vec![0.0, 0.0],
            high: vec![(width - 1) as f64, (height - 1) as f64],
            values: None,
        };
        let action_space = Space {
            names: vec!["dx".into(), "dy".into()],
            low: vec![-1.0, -1.0],
            high: vec![1.0, 1.0],
            values: Some(MOVES.iter().map(|m| m.to_vec()).collect()),
        };
        let open: Vec<(i64, i64)> = (0..height)
            .flat_map(|y| (0..width).map(move |x| (x, y)))
            .filter(|(x, y)| cells[y * width + x] != Cell::Obstacle)
            .map(|(x, y)| (x as i64, y as i64))
            .collect();
        let rollout_length = mean_manhattan(&open).round().max(1.0) as usize;
        Ok(Self {
            feature_map: GridFeatures::Scaled,
            width,
            height,
            cells,
            rollout_length,
            map: map.iter().map(|r| r.as_ref().to_string()).collect(),
            state_space,
            action_space,
        })
    }

    /// The same world with MDE features `f`.
    pub fn with_features(self, f: GridFeatures) -> Self {
        Self {
            feature_map: f,
            ..self
        }
    }

    /// The default 12×12 layout.
    pub fn default_layout() -> Self {
        Self::new(&DEFAULT_MAP).expect("the default map is valid")
    }

    /// Width (number of columns).
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height (number of rows).
    pub fn height(&self) -> usize {
        self.height
    }

    /// The map as given.
    pub fn map(&self) -> &[String] {
        &self.map
    }

    /// The cell at integer coordinates, or `None` off the grid.
    pub fn cell(&self, x: i64, y: i64) -> Option<Cell> {
        if x < 0 || y < 0 || x as usize >= self.width || y as usize >= self.height {
            return None;
        }
        Some(self.cells[y as usize * self.width + x as usize])
    }

    /// The cells that are not obstacles, as `[x, y]` states.
    pub fn open_cells(&self) -> Vec<[f64; 2]> {
        let mut out = Vec::new();
        for y in 0..self.height {
            for x in 0..self.width {
                if self.cells[y * self.width + x] != Cell::Obstacle {
                    out.push([x as f64, y as f64]);
                }
            }
        }
        out
    }

    fn check_cell(&self, v: &[f64], what: &str) -> Result<(), DomainError> {
        self.state_space.check(v)?;
        if v.iter().any(|c| c.fract() != 0.0) {
            return Err(DomainError::new(format!(
                "{what} {v:?} must have integer coordinates (a cell [x, y])"
            )));
        }
        Ok(())
    }
}

impl IcyGridworld {
    /// The move that brings `s` closest to `target`; ties are broken at random.
    pub fn steer_toward(&self, s: &[f64], target: &[f64], rng: &mut dyn RngCore) -> Vec<f64> {
        let mut best = f64::INFINITY;
        let mut ties: [usize; 4] = [0; 4];
        let mut n_ties = 0;
        for (i, m) in MOVES.iter().enumerate() {
            let d = euclidean(&[s[0] + m[0], s[1] + m[1]], target);
            if d < best - 1e-12 {
                best = d;
                ties[0] = i;
                n_ties = 1;
            } else if (d - best).abs() <= 1e-12 {
                ties[n_ties] = i;
                n_ties += 1;
            }
        }
        MOVES[ties[rng.random_range(0..n_ties)]].to_vec()
    }
}

impl Domain for IcyGridworld {
    fn kind(&self) -> &'static str {
        "icy_gridworld"
    }

    fn state_space(&self) -> &Space {
        &self.state_space
    }

    fn action_space(&self) -> &Space {
        &self.action_space
    }

    fn dynamics(&self) -> &dyn DynamicsModel {
        self
    }

    fn distance(&self, predicted: &[f64], observed: &[f64]) -> f64 {
        euclidean(predicted, observed)
    }

    fn default_d_max(&self) -> f64 {
        0.1
    }

    fn feature_dim(&self) -> usize {
        match self.feature_map {
            GridFeatures::Scaled => 4,
            GridFeatures::PerMove => 3 * MOVES.len(),
        }
    }

    /// [`GridFeatures::Scaled`]: `(x, y)` scaled by the grid, then the move scaled from
    /// `[-1, 1]` to `[0, 1]`. [`GridFeatures::PerMove`]: for move `k`, the scaled `(x, y)` at
    /// positions `2k, 2k+1` (zeros elsewhere), then the move one-hot.
    fn features(&self, s: &[f64], a: &[f64], _s_pred: &[f64]) -> Vec<f64> {
        match self.feature_map {
            GridFeatures::Scaled => self
                .state_space
                .to_unit(s)
                .chain(self.action_space.to_unit(a))
                .collect(),
            GridFeatures::PerMove => {
                // The move the action is, within the slack the action space allows it.
                let k = MOVES
                    .iter()
                    .position(|m| {
                        m.iter()
                            .zip(a)
                            .all(|(p, q)| (p - q).abs() <= BOUND_TOLERANCE)
                    })
                    .unwrap_or(0);
                let mut f = vec![0.0; 3 * MOVES.len()];
                for (i, u) in self.state_space.to_unit(s).enumerate() {
                    f[2 * k + i] = u;
                }
                f[2 * MOVES.len() + k] = 1.0;
                f
            }
        }
    }

    fn feature_map(&self) -> FeatureMap {
        let state = &self.state_space;
        match self.feature_map {
            GridFeatures::Scaled => FeatureMap::UnitBox {
                state_low: state.low.clone(),
                state_high: state.high.clone(),
                action_low: self.action_space.low.clone(),
                action_high: self.action_space.high.clone(),
                state_components: vec![0, 1],
                action_components: vec![0, 1],
                action_length: false,
                prediction_components: vec![],
                weights: vec![],
                move_length: false,
                periodic: Vec::new(),
            },
            GridFeatures::PerMove => FeatureMap::PerMove {
                state_low: state.low.clone(),
                state_high: state.high.clone(),
                moves: MOVES.iter().map(|m| m.to_vec()).collect(),
                tolerance: BOUND_TOLERANCE,
            },
        }
    }

    fn feature_names(&self) -> Vec<String> {
        match self.feature_map {
            GridFeatures::Scaled => ["x", "y", "dx", "dy"].map(String::from).to_vec(),
            GridFeatures::PerMove => {
                let moves = ["right", "left", "up", "down"];
                moves
                    .iter()
                    .flat_map(|m| [format!("x|{m}"), format!("y|{m}")])
                    .chain(moves.iter().map(|m| format!("is_{m}")))
                    .collect()
            }
        }
    }

    fn validate_state(&self, s: &[f64]) -> Result<(), DomainError> {
        self.check_cell(s, "state")
    }

    fn validate_observed_state(&self, s: &[f64]) -> Result<(), DomainError> {
        self.check_cell(s, "state")
    }

    fn validate_goal(&self, goal: &[f64]) -> Result<(), DomainError> {
        self.check_cell(goal, "goal")
    }

    fn is_goal(&self, s: &[f64], goal: &[f64]) -> bool {
        euclidean(s, goal) < 0.5
    }

    fn edge_allowed(&self, s: &[f64], _a: &[f64], s_pred: &[f64]) -> bool {
        // The model clamps to the grid, so a move off the edge predicts no progress.
        euclidean(s, s_pred) > 0.5
    }

    /// Each cell × each move the model allows (obstacles included: the model does not know
    /// them).
    fn finite_state_actions(&self) -> Option<Vec<(Vec<f64>, Vec<f64>)>> {
        let mut out = Vec::new();
        for y in 0..self.height {
            for x in 0..self.width {
                let c = [x as f64, y as f64];
                for m in MOVES {
                    if self.edge_allowed(&c, &m, &self.predict(&c, &m)) {
                        out.push((c.to_vec(), m.to_vec()));
                    }
                }
            }
        }
        Some(out)
    }

    fn sample_state(&self, rng: &mut dyn RngCore) -> Vec<f64> {
        vec![
            rng.random_range(0..self.width) as f64,
            rng.random_range(0..self.height) as f64,
        ]
    }

    fn goal_target(&self, goal: &[f64], _rng: &mut dyn RngCore) -> Vec<f64> {
        goal.to_vec()
    }

    fn state_metric(&self, a: &[f64], b: &[f64]) -> f64 {
        euclidean(a, b)
    }

    fn steer(&self, s: &[f64], target: &[f64], rng: &mut dyn RngCore) -> Vec<Vec<f64>> {
        vec![self.steer_toward(s, target, rng)]
    }

    fn sample_action(&self, _s: &[f64], rng: &mut dyn RngCore) -> Vec<f64> {
        MOVES[rng.random_range(0..4)].to_vec()
    }

    /// The mean Manhattan distance between two open cells (8 on the default map): as long as a
    /// typical goal-reaching trajectory, so that the `random` strategy executes about as many
    /// transitions per trajectory as the goal-conditioned ones and the strategies are compared
    /// on equal data.
    fn rollout_length(&self) -> usize {
        self.rollout_length
    }

    /// Start and goal uniform over the cells that are not obstacles (free or ice), distinct.
    fn sample_problem(&self, rng: &mut dyn RngCore) -> Problem {
        let open = self.open_cells();
        let i = rng.random_range(0..open.len());
        let mut j = rng.random_range(0..open.len() - 1);
        if j >= i {
            j += 1;
        }
        Problem::sampled(open[i].to_vec(), open[j].to_vec())
    }
}

impl LocalModel for IcyGridworld {
    /// The robot moves to the intended cell, clamped to the grid; ice and obstacles are unknown to
    /// the model.
    fn predict(&self, s: &[f64], a: &[f64]) -> Vec<f64> {
        let mut next = vec![s[0] + a[0], s[1] + a[1]];
        self.state_space.clamp(&mut next);
        next
    }
}

/// Mean Manhattan distance over distinct pairs of cells (0 for fewer than two).
fn mean_manhattan(cells: &[(i64, i64)]) -> f64 {
    let n = cells.len();
    if n < 2 {
        return 0.0;
    }
    let mut total = 0i64;
    for (i, a) in cells.iter().enumerate() {
        for b in &cells[i + 1..] {
            total += (a.0 - b.0).abs() + (a.1 - b.1).abs();
        }
    }
    total as f64 / (n * (n - 1) / 2) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn model_moves_to_the_intended_cell_clamped_to_the_grid() {
        let g = IcyGridworld::default_layout();
        assert_eq!(g.predict(&[3.0, 3.0], &[1.0, 0.0]), vec![4.0, 3.0]);
        assert_eq!(g.predict(&[0.0, 3.0], &[-1.0, 0.0]), vec![0.0, 3.0]);
        assert_eq!(g.predict(&[0.0, 11.0], &[0.0, 1.0]), vec![0.0, 11.0]);
    }

    #[test]
    fn random_rollouts_are_as_long_as_a_typical_problem() {
        assert_eq!(mean_manhattan(&[(0, 0), (3, 4)]), 7.0);
        assert_eq!(mean_manhattan(&[(0, 0), (1, 0), (0, 1)]), 4.0 / 3.0);
        let g = IcyGridworld::default_layout();
        assert_eq!(g.rollout_length(), 8);
    }

    #[test]
    fn per_move_features_give_each_move_its_own_coordinates() {
        let g = IcyGridworld::default_layout().with_features(GridFeatures::PerMove);
        assert_eq!(g.feature_dim(), 12);
        let f = g.features(&[11.0, 0.0], &[0.0, 1.0], &[]);
        assert_eq!(
            f,
            vec![0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]
        );
        assert_eq!(g.feature_names().len(), 12);
        assert_eq!(g.feature_names()[4], "x|up");
    }

    #[test]
    fn features_live_in_the_unit_box() {
        let g = IcyGridworld::default_layout();
        let f = g.features(&[11.0, 0.0], &[-1.0, 0.0], &[]);
        assert_eq!(f, vec![1.0, 0.0, 0.0, 0.5]);
    }

    #[test]
    fn rejects_bad_maps_and_cells() {
        assert!(IcyGridworld::new(&["..", "."]).is_err());
        assert!(IcyGridworld::new(&[".x"]).is_err());
        assert!(IcyGridworld::new(&["#."]).is_err());
        let g = IcyGridworld::default_layout();
        assert!(g.validate_state(&[1.5, 2.0]).is_err());
        assert!(g.validate_state(&[12.0, 2.0]).is_err());
        assert!(g.validate_action(&[1.0, 1.0]).is_err());
        assert!(g.validate_action(&[0.0, -1.0]).is_ok());
    }
}
