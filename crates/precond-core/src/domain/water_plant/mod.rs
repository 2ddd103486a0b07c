//! The water-plant domain (the paper's plant-watering scenario, in 2D): its model, distance,
//! goal, approximate collision checker and samplers. The true dynamics (swept collisions with the
//! leaves, water as particles deflected by them) live in `crate::sim::water_plant`.
//!
//! # Scene and units
//!
//! A vertical plane; `x` to the right, `y` up, lengths in metres, angles in radians, the ground at
//! `y = 0`. Water is counted in *units*: the source starts with one unit, and a pour releases at
//! most one unit (the paper scales volumes so that one unit is poured out).
//!
//! - **Source container**: a `0.12 × 0.20` m rectangle (a jug), open at the top. Its pose
//!   `(x, y, θ)` is the centre of the rectangle (its rotation centre) and its tilt
//!   `θ ∈ [0, 150°]`, measured clockwise from upright, i.e. towards `+x`: it pours over its right
//!   rim corner, the *lip* (see [`Scene::lip`]). Its centre stays in `x ∈ [−1, 0.75]`,
//!   `y ∈ [0.25, 1.75]`.
//! - **Target container**: a fixed open box (a planter), outer `x ∈ [−0.20, 0.20]`,
//!   `y ∈ [0, 0.30]`, walls `0.025` thick, so its *opening* is `x ∈ (−0.175, 0.175)` at the rim
//!   height `y = 0.30`. Its pose in the state is the centre of its base, `(0, 0, 0)`.
//! - **Plant**: a pot (`x ∈ [0.30, 0.60]`, `y ∈ [0, 0.25]`) right of the target, a stem at
//!   `x ∈ [0.44, 0.46]` up to `y = 1.25`, and two leaves (polylines from the stem to the tip)
//!   over the target's opening: a lower leaf rising from the stem (`y = 0.70`) to a tip over the
//!   opening's centre (`(0, 0.95)`), so water that lands on it runs back to the stem and drops
//!   onto the pot; and an upper leaf arching over the whole opening (`y ≈ 1.10–1.25`) with its
//!   tip left of the target (`(−0.25, 1.10)`), so water runs off its tip or back to the stem.
//!   See [`Scene::default`] for the coordinates. Only the simulator and plots use the leaves;
//!   the model and the collision checker do not know them.
//!
//! So pours from below the lower leaf (the jug's centre at `y ≈ 0.45–0.80`) over the opening
//! succeed, pours over the leaves spill, and the model, which only asks whether the lip is over
//! the opening, trusts all of them.
//!
//! # State, action, model
//!
//! State (9 components, [`STATE_NAMES`]): `[src_x, src_y, src_theta, src_volume, tgt_x, tgt_y,
//! tgt_theta, tgt_volume, spilled]`. The target's pose is fixed (its bounds have zero width).
//!
//! Action (3 components): the target pose `[x, y, theta]` of the source container, within the same
//! bounds as the source's pose. An action either **translates** (changes `x, y`, keeps `θ`) or
//! **rotates** (changes `θ` about the container's centre, keeps `x, y`), never both (within
//! [`MOTION_TOLERANCE`]). Planned actions always satisfy this ([`Domain::edge_allowed`], `steer`,
//! `sample_action`). A *posted* action that does both is rejected by [`Domain::validate_step`];
//! should one reach `predict` or the simulator anyway it is read as "translate, then rotate".
//!
//! The model `f̂` (the paper's analytical model): the source ends exactly at the commanded pose;
//! if its tilt is then at least the pour angle (130°) it pours `min(src_volume, 1)` units, all
//! into the target if the lip is above the target's opening (strictly inside the opening's `x`
//! range and above the rim), else all spilled. Leaves and collisions are ignored.
//!
//! Distance: `d = ‖src_xy − src_xy'‖ + ‖tgt_xy − tgt_xy'‖ + (|src_vol − src_vol'| + |tgt_vol −
//! tgt_vol'|) / 2`: the sum of both containers' position distances (metres; tilts are not
//! positions) plus the mean volume deviation of the two containers (units). `d_max = 0.1`.
//!
//! Features `φ(s, a)` (the paper's real scenario uses the action only): `[x, y, θ]` of the action
//! scaled to the unit box by the action bounds, and a fourth component, `1` when the action
//! rotates and `0` when it translates (or stays). The flag lets the GP tell a pour at `(x, y, θ)`
//! from a translation of an already tilted container to the same pose; for rotations `(x, y)` is
//! where the container pours from, for translations where it moves to.
//!
//! Goal: `[v]`, the volume wanted in the target (`0 < v ≤ 1`; problems use `[1.0]`). A state is a
//! goal when the target holds at least `0.98 v` and at most `0.02 v` has been spilled.

use super::{Domain, DomainError, DynamicsModel, FeatureMap, LocalModel, Problem, Space};
use rand::{Rng, RngCore};
use std::f64::consts::PI;

mod geometry;
mod scene;

pub use geometry::{Rect, Segment, Vec2, convex_hull, convex_overlap};
pub use scene::{Leaf, Pose, Scene};

/// Names of the state components, in order.
pub const STATE_NAMES: [&str; 9] = [
    "src_x",
    "src_y",
    "src_theta",
    "src_volume",
    "tgt_x",
    "tgt_y",
    "tgt_theta",
    "tgt_volume",
    "spilled",
];

/// Index of the source's `x` in the state.
pub const SRC_X: usize = 0;
/// Index of the source's `y` in the state.
pub const SRC_Y: usize = 1;
/// Index of the source's tilt in the state.
pub const SRC_THETA: usize = 2;
/// Index of the source's volume in the state.
pub const SRC_VOLUME: usize = 3;
/// Index of the target's `x` in the state.
pub const TGT_X: usize = 4;
/// Index of the target's `y` in the state.
pub const TGT_Y: usize = 5;
/// Index of the target's tilt in the state.
pub const TGT_THETA: usize = 6;
/// Index of the target's volume in the state.
pub const TGT_VOLUME: usize = 7;
/// Index of the spilled volume in the state.
pub const SPILLED: usize = 8;

/// Water in the scene (units): what the source holds at the start of a problem.
pub const TOTAL_WATER: f64 = 1.0;

/// The most a single pour releases (units).
pub const POUR_VOLUME: f64 = 1.0;

/// Below this change (metres or radians) a pose component counts as unchanged, when classifying
/// an action as a translation or a rotation.
pub const MOTION_TOLERANCE: f64 = 1e-6;

/// Fraction of the goal volume that may be missing from the target, and that may be spilled.
pub const GOAL_TOLERANCE: f64 = 0.02;

/// Metres per radian of tilt in [`Domain::state_metric`] (about the lip's distance from the
/// centre), so that tilts and positions compare.
const TILT_METRIC_SCALE: f64 = 0.12;

/// Angle between two samples of the collision checker's rotation sweep (radians).
const CHECK_ROTATION_STEP: f64 = 2.0 * PI / 180.0;

/// What an action does to the source, relative to the state it is taken in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Motion {
    /// Neither position nor tilt changes.
    Stay,
    /// The position changes, the tilt does not.
    Translate,
    /// The tilt changes, the position does not.
    Rotate,
    /// Both change: not allowed in plans nor in posted transitions.
    TranslateAndRotate,
}

/// The water-plant domain (see the module docs).
#[derive(Debug, Clone)]
pub struct WaterPlant {
    scene: Scene,
    state_space: Space,
    action_space: Space,
}

impl Default for WaterPlant {
    fn default() -> Self {
        Self::new(Scene::default()).expect("the default scene is valid")
    }
}

impl WaterPlant {
    /// Checks the scene and builds the domain.
    pub fn new(scene: Scene) -> Result<Self, DomainError> {
        scene.check()?;
        let t = scene.target_pose();
        let (lo, hi) = (scene.source_low, scene.source_high);
        let state_space = Space {
            names: STATE_NAMES.iter().map(|s| s.to_string()).collect(),
            low: vec![lo[0], lo[1], lo[2], 0.0, t[0], t[1], t[2], 0.0, 0.0],
            high: vec![
                hi[0],
                hi[1],
                hi[2],
                TOTAL_WATER,
                t[0],
                t[1],
                t[2],
                TOTAL_WATER,
                TOTAL_WATER,
            ],
            values: None,
        };
        let action_space = Space {
            names: vec!["x".into(), "y".into(), "theta".into()],
            low: lo.to_vec(),
            high: hi.to_vec(),
            values: None,
        };
        Ok(Self {
            scene,
            state_space,
            action_space,
        })
    }

    /// The scene (geometry, nominal leaves, bounds), e.g. to draw it.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// The start state of a problem with the source's centre at `(x, y)`: upright, holding
    /// [`TOTAL_WATER`]; the target empty; nothing spilled.
    pub fn start_state(&self, x: f64, y: f64) -> Vec<f64> {
        let t = self.scene.target_pose();
        vec![x, y, 0.0, TOTAL_WATER, t[0], t[1], t[2], 0.0, 0.0]
    }

    /// Classifies action `a` taken in state `s` (tolerance [`MOTION_TOLERANCE`]).
    pub fn motion(&self, s: &[f64], a: &[f64]) -> Motion {
        let moves = (a[0] - s[SRC_X]).hypot(a[1] - s[SRC_Y]) > MOTION_TOLERANCE;
        let turns = (a[2] - s[SRC_THETA]).abs() > MOTION_TOLERANCE;
        match (moves, turns) {
            (false, false) => Motion::Stay,
            (true, false) => Motion::Translate,
            (false, true) => Motion::Rotate,
            (true, true) => Motion::TranslateAndRotate,
        }
    }

    /// The planned action `a`, planned from state `planned`, re-expressed from the state the
    /// robot is actually in (`actual`) so that it keeps its form: a planned rotation tilts to the
    /// planned angle where the source actually is; a planned translation moves to the planned
    /// position at the actual tilt. Use it to execute a plan open loop after a deviation without
    /// producing actions that both translate and rotate; others are returned unchanged.
    pub fn reanchor(&self, planned: &[f64], a: &[f64], actual: &[f64]) -> Vec<f64> {
        match self.motion(planned, a) {
            Motion::Rotate => vec![actual[SRC_X], actual[SRC_Y], a[2]],
            Motion::Translate => vec![a[0], a[1], actual[SRC_THETA]],
            Motion::Stay | Motion::TranslateAndRotate => a.to_vec(),
        }
    }

    /// Whether the source, as it moves from pose `from` to pose `to` (a translation at
    /// `from.theta`, then a rotation to `to.theta`), stays clear of the fixed obstacles (the
    /// target, the pot and the stem; not the leaves).
    pub fn sweep_is_free(&self, from: Pose, to: Pose) -> bool {
        let obstacles = self.scene.fixed_obstacles();
        let hits = |poly: &[Vec2]| obstacles.iter().any(|o| convex_overlap(poly, o));
        // Translation: the swept area of a translated convex polygon is the hull of its start
        // and end positions.
        let mid = Pose {
            theta: from.theta,
            ..to
        };
        let mut pts = [[Vec2::default(); 4]; 2];
        pts[0] = self.scene.source_corners(from);
        pts[1] = self.scene.source_corners(mid);
        let mut flat: Vec<Vec2> = pts.iter().flatten().copied().collect();
        if hits(&convex_hull(&mut flat)) {
            return false;
        }
        // Rotation: sampled tilts.
        let dtheta = to.theta - from.theta;
        let n = (dtheta.abs() / CHECK_ROTATION_STEP).ceil() as usize;
        (1..=n).all(|k| {
            let pose = Pose {
                theta: from.theta + dtheta * k as f64 / n as f64,
                ..mid
            };
            !hits(&self.scene.source_corners(pose))
        })
    }

    /// The volumes after the source, at `pose`, pours per the model (unchanged when it does not
    /// pour). Returns `(src_volume, tgt_volume, spilled)`.
    fn model_pour(&self, pose: Pose, src: f64, tgt: f64, spilled: f64) -> (f64, f64, f64) {
        if pose.theta < self.scene.pour_angle || src <= 0.0 {
            return (src, tgt, spilled);
        }
        let poured = src.min(POUR_VOLUME);
        if self.scene.above_opening(self.scene.lip(pose)) {
            (src - poured, tgt + poured, spilled)
        } else {
            (src - poured, tgt, spilled + poured)
        }
    }

    fn clamp_pose(&self, a: &[f64]) -> Pose {
        let (lo, hi) = (self.scene.source_low, self.scene.source_high);
        Pose {
            x: a[0].clamp(lo[0], hi[0]),
            y: a[1].clamp(lo[1], hi[1]),
            theta: a[2].clamp(lo[2], hi[2]),
        }
    }

    fn uniform(rng: &mut dyn RngCore, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * rng.random::<f64>()
    }

    fn translation_towards(&self, s: &[f64], to: Vec2) -> Vec<f64> {
        let from = Vec2::new(s[SRC_X], s[SRC_Y]);
        let mut d = to - from;
        let len = d.norm();
        if len > self.scene.max_translation {
            d = d * (self.scene.max_translation / len);
        }
        let (lo, hi) = (self.scene.source_low, self.scene.source_high);
        vec![
            (from.x + d.x).clamp(lo[0], hi[0]),
            (from.y + d.y).clamp(lo[1], hi[1]),
            s[SRC_THETA],
        ]
    }
}

impl WaterPlant {
    /// Either a translation towards the target's position (at most `max_translation` long) or a
    /// rotation to the target's tilt: the one that is needed when only one is, else either with
    /// equal probability.
    pub fn steer_toward(&self, s: &[f64], target: &[f64], rng: &mut dyn RngCore) -> Vec<f64> {
        let to = Vec2::new(target[SRC_X], target[SRC_Y]);
        let moves = (to - Vec2::new(s[SRC_X], s[SRC_Y])).norm() > MOTION_TOLERANCE;
        let turns = (target[SRC_THETA] - s[SRC_THETA]).abs() > MOTION_TOLERANCE;
        let translate = match (moves, turns) {
            (true, false) => true,
            (false, true) => false,
            _ => rng.random_bool(0.5),
        };
        if translate {
            self.translation_towards(s, to)
        } else {
            let (lo, hi) = (self.scene.source_low[2], self.scene.source_high[2]);
            vec![s[SRC_X], s[SRC_Y], target[SRC_THETA].clamp(lo, hi)]
        }
    }
}

impl Domain for WaterPlant {
    /// The action must not both translate and rotate. (A posted action that does neither is
    /// accepted: the robot stood still.)
    fn validate_step(&self, s: &[f64], a: &[f64]) -> Result<(), DomainError> {
        if self.motion(s, a) == Motion::TranslateAndRotate {
            return Err(DomainError::new(format!(
                "the action {a:?} both moves the source from ({}, {}) and tilts it from {}; an \
                 action either translates (keep theta) or rotates (keep x and y)",
                s[SRC_X], s[SRC_Y], s[SRC_THETA]
            )));
        }
        Ok(())
    }

    fn kind(&self) -> &'static str {
        "water_plant"
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

    /// Sum of both containers' position distances plus the mean volume deviation of the two
    /// containers (see the module docs).
    fn distance(&self, p: &[f64], o: &[f64]) -> f64 {
        let src = (p[SRC_X] - o[SRC_X]).hypot(p[SRC_Y] - o[SRC_Y]);
        let tgt = (p[TGT_X] - o[TGT_X]).hypot(p[TGT_Y] - o[TGT_Y]);
        let vol =
            0.5 * ((p[SRC_VOLUME] - o[SRC_VOLUME]).abs() + (p[TGT_VOLUME] - o[TGT_VOLUME]).abs());
        src + tgt + vol
    }

    fn default_d_max(&self) -> f64 {
        0.1
    }

    fn feature_dim(&self) -> usize {
        4
    }

    /// The action `(x, y, θ)` scaled by the action bounds, then `1` for a rotation, `0` otherwise.
    fn features(&self, s: &[f64], a: &[f64], _s_pred: &[f64]) -> Vec<f64> {
        let rotates = matches!(
            self.motion(s, a),
            Motion::Rotate | Motion::TranslateAndRotate
        );
        self.action_space
            .to_unit(a)
            .map(|v| v.clamp(0.0, 1.0))
            .chain(std::iter::once(if rotates { 1.0 } else { 0.0 }))
            .collect()
    }

    fn feature_map(&self) -> FeatureMap {
        FeatureMap::ActionAndRotation {
            action_low: self.action_space.low.clone(),
            action_high: self.action_space.high.clone(),
            state_angle: SRC_THETA,
            action_angle: 2,
            tolerance: MOTION_TOLERANCE,
        }
    }

    fn feature_names(&self) -> Vec<String> {
        ["x", "y", "theta", "rotation"].map(String::from).to_vec()
    }

    /// `[v]` with `0 < v ≤ 1`: the volume wanted in the target (units).
    fn validate_goal(&self, goal: &[f64]) -> Result<(), DomainError> {
        if goal.len() != 1 {
            return Err(DomainError::new(format!(
                "expected 1 component (tgt_volume), got {}",
                goal.len()
            )));
        }
        let v = goal[0];
        if !(v.is_finite() && v > 0.0 && v <= TOTAL_WATER) {
            return Err(DomainError::new(format!(
                "component 0 (tgt_volume) = {v} must be a number in (0, {TOTAL_WATER}]"
            )));
        }
        Ok(())
    }

    /// The target holds at least `0.98 v` and at most `0.02 v` has been spilled.
    fn is_goal(&self, s: &[f64], goal: &[f64]) -> bool {
        let v = goal[0];
        s[TGT_VOLUME] >= (1.0 - GOAL_TOLERANCE) * v - 1e-9
            && s[SPILLED] <= GOAL_TOLERANCE * v + 1e-9
    }

    /// The action translates or rotates (not both, not neither), the predicted state lies in the
    /// bounds, and the source's sweep misses the target container, the pot and the stem (the
    /// checker does not know the leaves).
    fn edge_allowed(&self, s: &[f64], a: &[f64], s_pred: &[f64]) -> bool {
        if !matches!(self.motion(s, a), Motion::Translate | Motion::Rotate) {
            return false;
        }
        if self.state_space.check(s_pred).is_err() {
            return false;
        }
        self.sweep_is_free(Pose::from_slice(s), Pose::from_slice(s_pred))
    }

    /// The source's pose uniform over its bounds; the target's volume uniform in `[0, 1]` with
    /// the rest in the source and nothing spilled (the planner never aims to spill).
    fn sample_state(&self, rng: &mut dyn RngCore) -> Vec<f64> {
        let (lo, hi) = (self.scene.source_low, self.scene.source_high);
        let mut s = self.start_state(
            Self::uniform(rng, lo[0], hi[0]),
            Self::uniform(rng, lo[1], hi[1]),
        );
        s[SRC_THETA] = Self::uniform(rng, lo[2], hi[2]);
        let tgt = Self::uniform(rng, 0.0, TOTAL_WATER);
        s[TGT_VOLUME] = tgt;
        s[SRC_VOLUME] = TOTAL_WATER - tgt;
        s
    }

    /// A source pose that pours over the opening per the model: tilt uniform in
    /// `[pour angle, max tilt]`, the lip uniform over the opening's width, the centre high enough
    /// for the tilted container to clear the rim (up to the top of the workspace: the domain does
    /// not know where the leaves are); the target holds `v`, the source the rest.
    fn goal_target(&self, goal: &[f64], rng: &mut dyn RngCore) -> Vec<f64> {
        let sc = &self.scene;
        let (lo, hi) = (sc.source_low, sc.source_high);
        let theta = Self::uniform(rng, sc.pour_angle.max(lo[2]), hi[2]);
        let (o_lo, o_hi, rim) = sc.opening();
        let margin = 0.1 * (o_hi - o_lo);
        let lip_x = Self::uniform(rng, o_lo + margin, o_hi - margin);
        let x = (lip_x - sc.lip_offset(theta).x).clamp(lo[0], hi[0]);
        let y_low = (rim + sc.source_radius() + 0.005).clamp(lo[1], hi[1]);
        let y = Self::uniform(rng, y_low, hi[1]);
        let v = goal.first().copied().unwrap_or(TOTAL_WATER);
        let mut s = self.start_state(x, y);
        s[SRC_THETA] = theta;
        s[TGT_VOLUME] = v;
        s[SRC_VOLUME] = (TOTAL_WATER - v).max(0.0);
        s
    }

    /// Position distance plus `0.12 m/rad` × tilt difference, plus the differences of the
    /// target's and the spilled volumes (1 m per unit, so that nodes that spilled are far from
    /// every target).
    fn state_metric(&self, a: &[f64], b: &[f64]) -> f64 {
        let pose = (a[SRC_X] - b[SRC_X])
            .hypot(a[SRC_Y] - b[SRC_Y])
            .hypot(TILT_METRIC_SCALE * (a[SRC_THETA] - b[SRC_THETA]));
        pose + (a[TGT_VOLUME] - b[TGT_VOLUME]).abs() + (a[SPILLED] - b[SPILLED]).abs()
    }

    fn steer(&self, s: &[f64], target: &[f64], rng: &mut dyn RngCore) -> Vec<Vec<f64>> {
        vec![self.steer_toward(s, target, rng)]
    }

    /// With equal probability a translation in a uniform direction, uniform length up to
    /// `max_translation` (clipped to the bounds), or a rotation to a uniform tilt.
    fn sample_action(&self, s: &[f64], rng: &mut dyn RngCore) -> Vec<f64> {
        if rng.random_bool(0.5) {
            let angle = Self::uniform(rng, -PI, PI);
            let len = self.scene.max_translation * rng.random::<f64>();
            let to = Vec2::new(s[SRC_X], s[SRC_Y]) + Vec2::new(angle.cos(), angle.sin()) * len;
            self.translation_towards(s, to)
        } else {
            let (lo, hi) = (self.scene.source_low[2], self.scene.source_high[2]);
            vec![s[SRC_X], s[SRC_Y], Self::uniform(rng, lo, hi)]
        }
    }

    fn rollout_length(&self) -> usize {
        5
    }

    /// The source upright and full at a uniform position of the start region (left of the
    /// target); the goal `[1.0]`.
    fn sample_problem(&self, rng: &mut dyn RngCore) -> Problem {
        let (lo, hi) = (self.scene.start_low, self.scene.start_high);
        Problem::sampled(
            self.start_state(
                Self::uniform(rng, lo[0], hi[0]),
                Self::uniform(rng, lo[1], hi[1]),
            ),
            vec![TOTAL_WATER],
        )
    }
}

impl LocalModel for WaterPlant {
    /// The paper's analytical model (see the module docs).
    fn predict(&self, s: &[f64], a: &[f64]) -> Vec<f64> {
        let pose = self.clamp_pose(a);
        let (src, tgt, spilled) = self.model_pour(pose, s[SRC_VOLUME], s[TGT_VOLUME], s[SPILLED]);
        let mut next = s.to_vec();
        next[SRC_X] = pose.x;
        next[SRC_Y] = pose.y;
        next[SRC_THETA] = pose.theta;
        next[SRC_VOLUME] = src;
        next[TGT_VOLUME] = tgt;
        next[SPILLED] = spilled;
        next
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;
    use proptest::prelude::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn plant() -> WaterPlant {
        WaterPlant::default()
    }

    fn rng() -> ChaCha8Rng {
        ChaCha8Rng::seed_from_u64(11)
    }

    /// A rotation-only action that tilts to 135° where the source stands.
    fn pour_at(s: &[f64]) -> Vec<f64> {
        vec![s[0], s[1], 135f64.to_radians()]
    }

    #[test]
    fn the_state_space_names_and_bounds_every_component() {
        let w = plant();
        let ss = w.state_space();
        assert_eq!(ss.names, STATE_NAMES.map(String::from).to_vec());
        assert_eq!(ss.dim(), 9);
        assert_eq!(w.action_space().dim(), 3);
        // The target's pose is fixed.
        assert_eq!(ss.low[TGT_X], ss.high[TGT_X]);
        assert!(w.validate_state(&w.start_state(-0.5, 0.75)).is_ok());
        let mut moved = w.start_state(-0.5, 0.75);
        moved[TGT_X] = 0.05;
        assert!(w.validate_state(&moved).is_err());
    }

    #[test]
    fn the_model_translates_exactly_and_ignores_leaves() {
        let w = plant();
        let s = w.start_state(-0.25, 0.8);
        // Straight through the lower leaf: the model does not know it.
        let a = [0.1, 0.8, 0.0];
        let p = w.predict(&s, &a);
        assert_eq!(&p[..3], &a);
        assert_eq!(&p[3..], &s[3..]);
    }

    #[test]
    fn the_model_pours_one_unit_into_the_target_when_the_lip_is_over_the_opening() {
        let w = plant();
        let s = w.start_state(0.0, 0.625);
        let p = w.predict(&s, &pour_at(&s));
        assert_eq!((p[SRC_VOLUME], p[TGT_VOLUME], p[SPILLED]), (0.0, 1.0, 0.0));
        assert!(w.is_goal(&p, &[1.0]));
        // Also above the leaves (the model does not know them).
        let s = w.start_state(0.0, 1.5);
        let p = w.predict(&s, &pour_at(&s));
        assert_eq!(p[TGT_VOLUME], 1.0);
    }

    #[test]
    fn the_model_spills_when_the_lip_is_not_over_the_opening() {
        let w = plant();
        let s = w.start_state(-0.625, 0.75);
        let p = w.predict(&s, &pour_at(&s));
        assert_eq!((p[SRC_VOLUME], p[TGT_VOLUME], p[SPILLED]), (0.0, 0.0, 1.0));
        assert!(!w.is_goal(&p, &[1.0]));
    }

    #[test]
    fn the_model_does_not_pour_below_the_pour_angle() {
        let w = plant();
        let s = w.start_state(0.0, 0.625);
        let p = w.predict(&s, &[0.0, 0.625, 120f64.to_radians()]);
        assert_eq!(&p[3..], &s[3..]);
        let p = w.predict(&s, &[0.0, 0.625, 130f64.to_radians()]);
        assert_eq!(p[TGT_VOLUME], 1.0);
    }

    #[test]
    fn the_distance_adds_positions_and_the_mean_volume_deviation() {
        let w = plant();
        let a = w.start_state(0.0, 0.5);
        let mut b = a.clone();
        b[SRC_X] += 0.03;
        b[SRC_Y] += 0.04;
        b[SRC_THETA] += 1.0; // tilts are not positions
        b[SRC_VOLUME] = 0.0;
        b[TGT_VOLUME] = 0.6;
        b[SPILLED] = 0.4; // follows from the others
        assert_relative_eq!(
            w.distance(&a, &b),
            0.05 + 0.5 * (1.0 + 0.6),
            epsilon = 1e-12
        );
        assert_eq!(w.distance(&a, &a), 0.0);
        assert_eq!(w.default_d_max(), 0.1);
    }

    #[test]
    fn goals_need_the_volume_in_the_target_and_at_most_two_percent_spilled() {
        let w = plant();
        assert!(w.validate_goal(&[1.0]).is_ok());
        assert!(w.validate_goal(&[0.5]).is_ok());
        for bad in [vec![], vec![0.0], vec![1.5], vec![f64::NAN], vec![1.0, 0.0]] {
            assert!(w.validate_goal(&bad).is_err(), "{bad:?}");
        }
        let mut s = w.start_state(0.0, 0.625);
        s[SRC_VOLUME] = 0.0;
        s[TGT_VOLUME] = 0.98;
        s[SPILLED] = 0.02;
        assert!(w.is_goal(&s, &[1.0]));
        s[TGT_VOLUME] = 0.97;
        s[SPILLED] = 0.03;
        assert!(!w.is_goal(&s, &[1.0]));
        assert!(!w.is_goal(&w.start_state(0.0, 0.625), &[1.0]));
    }

    #[test]
    fn actions_either_translate_or_rotate() {
        let w = plant();
        let s = w.start_state(-0.5, 0.75);
        assert_eq!(w.motion(&s, &[-0.25, 0.75, 0.0]), Motion::Translate);
        assert_eq!(w.motion(&s, &[-0.5, 0.75, 1.0]), Motion::Rotate);
        assert_eq!(w.motion(&s, &[-0.5, 0.75, 0.0]), Motion::Stay);
        assert_eq!(
            w.motion(&s, &[-0.25, 0.75, 1.0]),
            Motion::TranslateAndRotate
        );
        // Posted: both is rejected, staying is accepted.
        assert!(w.validate_step(&s, &[-0.25, 0.75, 0.0]).is_ok());
        assert!(w.validate_step(&s, &[-0.5, 0.75, 2.3]).is_ok());
        assert!(w.validate_step(&s, &[-0.5, 0.75, 0.0]).is_ok());
        let err = w.validate_step(&s, &[-0.25, 0.75, 1.0]).unwrap_err();
        assert!(err.reason.contains("either translates"), "{err}");
        // Out of bounds, non-finite, wrong length.
        assert!(w.validate_action(&[-0.25, 0.75, 3.0]).is_err());
        assert!(w.validate_action(&[f64::NAN, 0.75, 0.0]).is_err());
        assert!(w.validate_action(&[0.0, 0.75]).is_err());
        // Planned: both and neither are not edges.
        for a in [[-0.25, 0.75, 1.0], [-0.5, 0.75, 0.0]] {
            assert!(!w.edge_allowed(&s, &a, &w.predict(&s, &a)), "{a:?}");
        }
        let a = [-0.25, 0.75, 0.0];
        assert!(w.edge_allowed(&s, &a, &w.predict(&s, &a)));
    }

    #[test]
    fn reanchoring_keeps_the_form_of_a_planned_action() {
        let w = plant();
        let planned = w.start_state(0.0, 0.6);
        let actual = w.start_state(-0.02, 0.58);
        let rot = [0.0, 0.6, 2.4];
        assert_eq!(w.reanchor(&planned, &rot, &actual), vec![-0.02, 0.58, 2.4]);
        let tr = [0.1, 0.6, 0.0];
        let mut tilted = actual.clone();
        tilted[SRC_THETA] = 0.3;
        assert_eq!(w.reanchor(&planned, &tr, &tilted), vec![0.1, 0.6, 0.3]);
        assert_eq!(
            w.motion(&tilted, &w.reanchor(&planned, &tr, &tilted)),
            Motion::Translate
        );
    }

    #[test]
    fn the_collision_checker_knows_the_target_pot_and_stem_but_not_the_leaves() {
        let w = plant();
        // Sweeping through the target container.
        let s = w.start_state(-0.5, 0.30);
        let a = [0.0, 0.30, 0.0];
        assert!(!w.edge_allowed(&s, &a, &w.predict(&s, &a)));
        // Through the stem.
        let s = w.start_state(0.25, 0.75);
        let a = [0.625, 0.75, 0.0];
        assert!(!w.edge_allowed(&s, &a, &w.predict(&s, &a)));
        // Through the lower leaf: allowed (the checker does not know leaves).
        let s = w.start_state(-0.25, 0.8);
        let a = [0.1, 0.8, 0.0];
        assert!(w.edge_allowed(&s, &a, &w.predict(&s, &a)));
        // Tilting low over the rim hits the target.
        let s = w.start_state(0.0, 0.4075);
        let a = pour_at(&s);
        assert!(!w.edge_allowed(&s, &a, &w.predict(&s, &a)));
        // Tilting well above the rim does not.
        let s = w.start_state(0.0, 0.55);
        let a = pour_at(&s);
        assert!(w.edge_allowed(&s, &a, &w.predict(&s, &a)));
    }

    #[test]
    fn problems_start_left_of_the_target_upright_and_full() {
        let w = plant();
        let mut r = rng();
        for _ in 0..100 {
            let p = w.sample_problem(&mut r);
            assert!(w.validate_state(p.start()).is_ok());
            assert!(w.validate_goal(p.goal()).is_ok());
            assert_eq!(p.goal().to_vec(), vec![1.0]);
            let corners = w.scene().source_corners(Pose::from_slice(p.start()));
            assert!(corners.iter().all(|c| c.x < w.scene().target.low.x));
            assert_eq!(p.start()[SRC_THETA], 0.0);
            assert_eq!(p.start()[SRC_VOLUME], 1.0);
            assert!(!w.is_goal(p.start(), p.goal()));
        }
    }

    #[test]
    fn goal_targets_pour_over_the_opening_per_the_model() {
        let w = plant();
        let mut r = rng();
        for _ in 0..200 {
            let g = w.goal_target(&[1.0], &mut r);
            assert!(w.validate_state(&g).is_ok(), "{g:?}");
            assert!(w.is_goal(&g, &[1.0]));
            let pose = Pose::from_slice(&g);
            assert!(pose.theta >= w.scene().pour_angle);
            assert!(w.scene().above_opening(w.scene().lip(pose)));
            // Pouring there straight from upright is a valid edge.
            let s = w.start_state(g[0], g[1]);
            let a = &g[..3];
            let p = w.predict(&s, a);
            assert!(w.edge_allowed(&s, a, &p), "{g:?}");
            assert!(w.is_goal(&p, &[1.0]));
        }
    }

    #[test]
    fn features_are_the_action_and_a_rotation_flag_in_the_unit_box() {
        let w = plant();
        let s = w.start_state(-0.125, 1.0);
        let f = w.features(&s, &[-0.125, 1.0, 150f64.to_radians()], &[]);
        assert_eq!(f.len(), w.feature_dim());
        assert_relative_eq!(f[0], 0.5, epsilon = 1e-12);
        assert_relative_eq!(f[1], 0.5, epsilon = 1e-12);
        assert_relative_eq!(f[2], 1.0, epsilon = 1e-12);
        assert_eq!(f[3], 1.0);
        let f = w.features(&s, &[0.75, 0.25, 0.0], &[]);
        assert_eq!(f, vec![1.0, 0.0, 0.0, 0.0]);
        assert_eq!(w.feature_names().len(), 4);
    }

    #[test]
    fn steering_picks_one_motion_and_respects_the_step_limit() {
        let w = plant();
        let mut r = rng();
        let s = w.start_state(-0.75, 0.5);
        // Only the position differs: a translation of at most max_translation.
        let mut t = w.start_state(0.75, 1.25);
        let a = w.steer_toward(&s, &t, &mut r);
        assert_eq!(w.motion(&s, &a), Motion::Translate);
        assert_relative_eq!((a[0] - s[0]).hypot(a[1] - s[1]), 0.35, epsilon = 1e-12);
        // Only the tilt differs: a rotation all the way.
        t = s.clone();
        t[SRC_THETA] = 2.4;
        assert_eq!(w.steer_toward(&s, &t, &mut r), vec![-0.75, 0.5, 2.4]);
    }

    #[test]
    fn the_default_scene_covers_part_of_the_opening_with_leaves() {
        let sc = Scene::default();
        let (lo, hi, rim) = sc.opening();
        assert!(lo < hi && rim > 0.0);
        // Some of the opening's width lies under a leaf, all leaves are above the rim with room
        // for the tilted source below the lower one.
        let lower = &sc.leaves[0];
        let min_leaf_y = lower
            .points
            .iter()
            .map(|p| p.y)
            .fold(f64::INFINITY, f64::min);
        assert!(min_leaf_y - rim > 2.0 * sc.source_radius() + 0.05);
        assert!(lower.points.iter().any(|p| p.x > lo && p.x < hi));
    }

    #[test]
    fn rejects_bad_scenes() {
        let bad = Scene {
            target_wall: 0.25,
            ..Scene::default()
        };
        assert!(WaterPlant::new(bad).is_err());
        let bad = Scene {
            leaves: vec![Leaf {
                points: vec![Vec2::new(0.0, 0.3)],
            }],
            ..Scene::default()
        };
        assert!(WaterPlant::new(bad).is_err());
        let bad = Scene {
            pour_angle: f64::NAN,
            ..Scene::default()
        };
        assert!(WaterPlant::new(bad).is_err());
    }

    #[test]
    fn geometry_overlap_and_hull() {
        let sq = Rect {
            low: Vec2::new(0.0, 0.0),
            high: Vec2::new(1.0, 1.0),
        }
        .corners();
        let seg_in = [Vec2::new(-1.0, 0.5), Vec2::new(2.0, 0.5)];
        let seg_out = [Vec2::new(-1.0, 1.5), Vec2::new(2.0, 1.2)];
        assert!(convex_overlap(&sq, &seg_in));
        assert!(!convex_overlap(&sq, &seg_out));
        let diamond = [
            Vec2::new(1.5, 0.5),
            Vec2::new(2.0, 1.0),
            Vec2::new(1.5, 1.5),
            Vec2::new(1.0 + 1e-9, 1.0),
        ];
        assert!(!convex_overlap(&sq, &diamond));
        let mut pts = vec![
            Vec2::new(0.0, 0.0),
            Vec2::new(1.0, 0.0),
            Vec2::new(0.5, 0.5),
            Vec2::new(1.0, 1.0),
            Vec2::new(0.0, 1.0),
        ];
        assert_eq!(convex_hull(&mut pts).len(), 4);
    }

    proptest! {
        #[test]
        fn planned_actions_satisfy_the_form_and_the_bounds(seed in 0u64..1000) {
            let w = plant();
            let mut r = ChaCha8Rng::seed_from_u64(seed);
            let s = w.sample_problem(&mut r).start().to_vec();
            let target = w.sample_state(&mut r);
            let goal = w.goal_target(&[1.0], &mut r);
            for a in [w.steer_toward(&s, &target, &mut r), w.steer_toward(&s, &goal, &mut r), w.sample_action(&s, &mut r)] {
                prop_assert!(w.validate_step(&s, &a).is_ok(), "{:?}", a);
                prop_assert!(w.validate_state(&w.predict(&s, &a)).is_ok());
                let m = w.motion(&s, &a);
                prop_assert!(m != Motion::TranslateAndRotate);
                if m == Motion::Translate {
                    prop_assert!((a[0] - s[0]).hypot(a[1] - s[1]) <= w.scene().max_translation + 1e-12);
                }
            }
        }

        #[test]
        fn the_model_conserves_water(x in -1.0f64..0.75, y in 0.25f64..1.75, th in 0.0f64..2.6) {
            let w = plant();
            let s = w.start_state(x, y);
            let p = w.predict(&s, &[x, y, th]);
            prop_assert!((p[SRC_VOLUME] + p[TGT_VOLUME] + p[SPILLED] - TOTAL_WATER).abs() < 1e-12);
        }
    }
}
