//! The generic kinematic domain: "the state moves by the action", for any robot whose model is
//! that simple. `f̂(s, a) = clip(s + a)` to the state bounds; Euclidean distance; optional
//! axis-aligned box obstacles for the approximate collision check; a goal is a state with a radius.

use super::{
    Domain, DomainError, DynamicsModel, FeatureMap, LocalModel, Problem, Space, check_goal_radius,
    check_magnitudes, euclidean, predicted_move_fraction, segment_clear, uniform_between,
};
use rand::RngCore;

/// An axis-aligned box that planned edges may not pass through.
#[derive(Debug, Clone, PartialEq)]
pub struct BoxObstacle {
    /// Lower corner.
    pub low: Vec<f64>,
    /// Upper corner.
    pub high: Vec<f64>,
}

impl BoxObstacle {
    /// Checks obstacle `k` of a state space of dimension `n`: `n` finite components per corner,
    /// `low ≤ high`.
    pub fn check(&self, k: usize, n: usize) -> Result<(), DomainError> {
        if self.low.len() != n || self.high.len() != n {
            return Err(DomainError::at(
                format!("obstacles[{k}]"),
                format!("low and high need {n} components, one per state component"),
            ));
        }
        for (corner, v) in [("low", &self.low), ("high", &self.high)] {
            check_magnitudes(&format!("obstacles[{k}].{corner}"), v)?;
        }
        if self.low.iter().chain(&self.high).any(|x| !x.is_finite())
            || self.low.iter().zip(&self.high).any(|(l, h)| l > h)
        {
            return Err(DomainError::at(
                format!("obstacles[{k}]"),
                "bounds must be finite with low ≤ high",
            ));
        }
        Ok(())
    }

    fn contains(&self, p: &[f64]) -> bool {
        p.iter()
            .zip(self.low.iter().zip(&self.high))
            .all(|(x, (lo, hi))| *x >= *lo && *x <= *hi)
    }
}

/// How a kinematic state-action is fed to the MDE.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
#[serde(rename_all = "snake_case")]
pub enum KinematicFeatures {
    /// `(s, a)`, each scaled to the unit box by its bounds.
    StateAction,
    /// `(s, a, clip(s + a))`: the state, the action and the state the model predicts, each
    /// scaled to the unit box. A deviation that depends on where a move ends (an obstacle it
    /// runs into, a patch where the robot slides) is then a function of a few features — the
    /// prediction's — that a kernel with per-feature length scales can follow, where over
    /// `(s, a)` alone it lies along the diagonal `s + a = const` and is spread over every
    /// feature.
    StateActionPrediction,
    /// `(s, a, clip(s + a), ‖clip(s + a) − s‖)`: the prediction's features and the length of
    /// the predicted move, as a fraction of the longest commandable one
    /// ([`predicted_move_fraction`]). A deviation that grows with the size of the move (the
    /// robot slides on after a push, turns on a slope by a share of each move) is then smooth
    /// in one feature instead of a cone around `a = 0`.
    #[default]
    StateActionPredictionLength,
}

impl KinematicFeatures {
    /// Whether the features include the model's prediction `clip(s + a)`.
    fn prediction(self) -> bool {
        self != Self::StateAction
    }

    /// Whether the features end with the length of the predicted move.
    fn move_length(self) -> bool {
        self == Self::StateActionPredictionLength
    }
}

/// By hand, so that a wrong name says which setting it is: the domain spec is a tagged enum,
/// whose variants' fields reach the request's error only as `domain`.
impl<'de> serde::Deserialize<'de> for KinematicFeatures {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let name = String::deserialize(d)?;
        match name.as_str() {
            "state_action" => Ok(Self::StateAction),
            "state_action_prediction" => Ok(Self::StateActionPrediction),
            "state_action_prediction_length" => Ok(Self::StateActionPredictionLength),
            _ => Err(serde::de::Error::custom(format!(
                "features: {name:?} is not a feature map; use state_action_prediction_length, \
                 state_action_prediction or state_action"
            ))),
        }
    }
}

/// The parameters of a kinematic domain, as given by a client.
#[derive(Debug, Clone, PartialEq)]
pub struct KinematicParams {
    /// Lower bounds of the state (also fixes the dimension `n`).
    pub state_low: Vec<f64>,
    /// Upper bounds of the state.
    pub state_high: Vec<f64>,
    /// Lower bounds of the action (each ≤ 0, so that the robot can stand still).
    pub action_low: Vec<f64>,
    /// Upper bounds of the action (each ≥ 0).
    pub action_high: Vec<f64>,
    /// Obstacles for the approximate collision check.
    pub obstacles: Vec<BoxObstacle>,
    /// A state within this Euclidean distance of the goal state has arrived.
    pub goal_radius: f64,
    /// What the MDE sees of a state-action.
    pub features: KinematicFeatures,
}

impl Default for KinematicParams {
    /// A unit square, moves of at most 0.1 per axis, no obstacles, goal radius 0.05.
    fn default() -> Self {
        Self {
            state_low: vec![0.0, 0.0],
            state_high: vec![1.0, 1.0],
            action_low: vec![-0.1, -0.1],
            action_high: vec![0.1, 0.1],
            obstacles: Vec::new(),
            goal_radius: 0.05,
            features: KinematicFeatures::default(),
        }
    }
}

/// The kinematic domain (see the module docs).
#[derive(Debug, Clone)]
pub struct Kinematic {
    params: KinematicParams,
    state_space: Space,
    action_space: Space,
    rollout_length: usize,
}

/// The fractions of the full step towards a target that steering offers (see
/// [`Kinematic`]'s `steer`).
pub const STEER_SCALES: [f64; 3] = [1.0, 0.5, 0.25];

impl Kinematic {
    /// Largest accepted state dimension.
    pub const MAX_DIM: usize = 32;

    /// Checks the parameters and builds the domain. Errors name the parameter.
    pub fn new(params: KinematicParams) -> Result<Self, DomainError> {
        let n = params.state_low.len();
        if n == 0 || n > Self::MAX_DIM {
            return Err(DomainError::at(
                "state_low",
                format!(
                    "the dimension must be between 1 and {}, got {n}",
                    Self::MAX_DIM
                ),
            ));
        }
        for (name, v) in [
            ("state_high", &params.state_high),
            ("action_low", &params.action_low),
            ("action_high", &params.action_high),
        ] {
            if v.len() != n {
                return Err(DomainError::at(
                    name,
                    format!("expected {n} components like state_low, got {}", v.len()),
                ));
            }
        }
        for (name, v) in [
            ("state_low", &params.state_low),
            ("state_high", &params.state_high),
            ("action_low", &params.action_low),
            ("action_high", &params.action_high),
        ] {
            check_magnitudes(name, v)?;
        }
        for i in 0..n {
            if params.state_low[i] >= params.state_high[i] {
                return Err(DomainError::at(
                    "state_high",
                    format!("component {i} must exceed state_low's"),
                ));
            }
            if params.action_low[i] > 0.0 {
                return Err(DomainError::at(
                    "action_low",
                    format!("component {i} must be ≤ 0 so that the robot can stand still"),
                ));
            }
            if params.action_high[i] < 0.0 {
                return Err(DomainError::at(
                    "action_high",
                    format!("component {i} must be ≥ 0 so that the robot can stand still"),
                ));
            }
            if params.action_low[i] == params.action_high[i] {
                return Err(DomainError::at(
                    "action_high",
                    format!("component {i} must exceed action_low's"),
                ));
            }
        }
        for (k, o) in params.obstacles.iter().enumerate() {
            o.check(k, n)?;
        }
        check_goal_radius("goal_radius", params.goal_radius)?;
        let names = |prefix: &str| (0..n).map(|i| format!("{prefix}{i}")).collect::<Vec<_>>();
        let state_space = Space {
            names: names("x"),
            low: params.state_low.clone(),
            high: params.state_high.clone(),
            values: None,
        };
        let action_space = Space {
            names: names("dx"),
            low: params.action_low.clone(),
            high: params.action_high.clone(),
            values: None,
        };
        let mut domain = Self {
            params,
            state_space,
            action_space,
            rollout_length: 1,
        };
        domain.rollout_length = domain.typical_path_steps();
        Ok(domain)
    }

    /// The steps of a straight, full-speed path between the start and goal of a random problem,
    /// averaged over 256 seeded problems and rounded: the length of a `random` rollout, so that
    /// every strategy executes about as many transitions per trajectory as a goal-reaching one.
    fn typical_path_steps(&self) -> usize {
        use rand::SeedableRng;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0x726f_6c6c);
        let n = 256;
        let total: f64 = (0..n)
            .map(|_| {
                let p = self.sample_problem(&mut rng);
                p.start()
                    .iter()
                    .zip(p.goal())
                    .enumerate()
                    .map(|(i, (s, g))| {
                        let limit = if g > s {
                            self.action_space.high[i]
                        } else {
                            -self.action_space.low[i]
                        };
                        if limit > 0.0 {
                            ((g - s).abs() / limit).ceil()
                        } else {
                            0.0
                        }
                    })
                    .fold(0.0, f64::max)
            })
            .sum();
        ((total / n as f64).round() as usize).clamp(1, 1000)
    }

    /// The parameters this domain was built from.
    pub fn params(&self) -> &KinematicParams {
        &self.params
    }

    /// Whether the point lies inside an obstacle.
    pub fn in_collision(&self, p: &[f64]) -> bool {
        self.params.obstacles.iter().any(|o| o.contains(p))
    }

    fn sample_free(&self, rng: &mut dyn RngCore) -> Vec<f64> {
        // Rejection sampling; obstacles covering the whole box would loop, so give up after a while
        // and return the last draw.
        let mut s = self.sample_state(rng);
        for _ in 0..1000 {
            if !self.in_collision(&s) {
                break;
            }
            s = self.sample_state(rng);
        }
        s
    }
}

impl Kinematic {
    /// The displacement to the target, shrunk uniformly until it fits the action bounds.
    pub fn steer_toward(&self, s: &[f64], target: &[f64], _rng: &mut dyn RngCore) -> Vec<f64> {
        let delta: Vec<f64> = s.iter().zip(target).map(|(x, t)| t - x).collect();
        let mut scale: f64 = 1.0;
        for (i, d) in delta.iter().enumerate() {
            let limit = if *d > 0.0 {
                self.action_space.high[i]
            } else {
                -self.action_space.low[i]
            };
            if d.abs() > limit {
                scale = scale.min(limit / d.abs());
            }
        }
        delta.iter().map(|d| d * scale).collect()
    }
}

impl Domain for Kinematic {
    fn kind(&self) -> &'static str {
        "kinematic"
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
        let n = self.state_space.dim();
        let f = self.params.features;
        if f.prediction() {
            3 * n + usize::from(f.move_length())
        } else {
            2 * n
        }
    }

    fn features(&self, s: &[f64], a: &[f64], _s_pred: &[f64]) -> Vec<f64> {
        let mut phi: Vec<f64> = self
            .state_space
            .to_unit(s)
            .chain(self.action_space.to_unit(a))
            .collect();
        let f = self.params.features;
        if f.prediction() {
            phi.extend(self.state_space.to_unit(&LocalModel::predict(self, s, a)));
        }
        if f.move_length() {
            let (state, action) = (&self.state_space, &self.action_space);
            phi.push(predicted_move_fraction(
                s,
                a,
                &state.low,
                &state.high,
                &action.low,
                &action.high,
            ));
        }
        phi
    }

    fn feature_map(&self) -> FeatureMap {
        let (state_low, state_high) = (self.state_space.low.clone(), self.state_space.high.clone());
        let (action_low, action_high) = (
            self.action_space.low.clone(),
            self.action_space.high.clone(),
        );
        match self.params.features {
            KinematicFeatures::StateAction => FeatureMap::UnitBox {
                state_low,
                state_high,
                action_low,
                action_high,
                state_components: (0..self.state_space.dim()).collect(),
                action_components: (0..self.action_space.dim()).collect(),
                action_length: false,
                prediction_components: vec![],
                weights: vec![],
                move_length: false,
                periodic: Vec::new(),
            },
            KinematicFeatures::StateActionPrediction
            | KinematicFeatures::StateActionPredictionLength => FeatureMap::KinematicPrediction {
                state_low,
                state_high,
                action_low,
                action_high,
                move_length: self.params.features.move_length(),
            },
        }
    }

    fn feature_names(&self) -> Vec<String> {
        let names = &self.state_space.names;
        let mut out: Vec<String> = names
            .iter()
            .chain(&self.action_space.names)
            .cloned()
            .collect();
        let f = self.params.features;
        if f.prediction() {
            out.extend(names.iter().map(|n| format!("predicted_{n}")));
        }
        if f.move_length() {
            out.push("predicted_move_length".to_string());
        }
        out
    }

    fn validate_goal(&self, goal: &[f64]) -> Result<(), DomainError> {
        self.state_space.check(goal)
    }

    fn is_goal(&self, s: &[f64], goal: &[f64]) -> bool {
        euclidean(s, goal) <= self.params.goal_radius
    }

    fn edge_allowed(&self, s: &[f64], _a: &[f64], s_pred: &[f64]) -> bool {
        if euclidean(s, s_pred) < 1e-12 {
            return false;
        }
        segment_clear(s, s_pred, |p| self.in_collision(p))
    }

    fn sample_state(&self, rng: &mut dyn RngCore) -> Vec<f64> {
        (0..self.state_space.dim())
            .map(|i| uniform_between(rng, self.state_space.low[i], self.state_space.high[i]))
            .collect()
    }

    fn goal_target(&self, goal: &[f64], _rng: &mut dyn RngCore) -> Vec<f64> {
        goal.to_vec()
    }

    fn state_metric(&self, a: &[f64], b: &[f64]) -> f64 {
        euclidean(a, b)
    }

    /// The step towards `target` as far as the action bounds allow, and the same direction at
    /// half and a quarter of that length ([`STEER_SCALES`]): the planner keeps the longest
    /// that is allowed and inside the precondition (where only short moves are trusted — a
    /// slippery patch, a wet floor — a full step would be refused every time).
    fn steer(&self, s: &[f64], target: &[f64], rng: &mut dyn RngCore) -> Vec<Vec<f64>> {
        let full = self.steer_toward(s, target, rng);
        STEER_SCALES
            .iter()
            .map(|k| full.iter().map(|x| x * k).collect())
            .collect()
    }

    fn sample_action(&self, _s: &[f64], rng: &mut dyn RngCore) -> Vec<f64> {
        (0..self.action_space.dim())
            .map(|i| uniform_between(rng, self.action_space.low[i], self.action_space.high[i]))
            .collect()
    }

    fn rollout_length(&self) -> usize {
        self.rollout_length
    }

    fn sample_problem(&self, rng: &mut dyn RngCore) -> Problem {
        let start = self.sample_free(rng);
        let mut goal = self.sample_free(rng);
        for _ in 0..1000 {
            if euclidean(&start, &goal) > 2.0 * self.params.goal_radius {
                break;
            }
            goal = self.sample_free(rng);
        }
        Problem::sampled(start, goal)
    }
}

impl LocalModel for Kinematic {
    fn predict(&self, s: &[f64], a: &[f64]) -> Vec<f64> {
        let mut next: Vec<f64> = s.iter().zip(a).map(|(x, d)| x + d).collect();
        self.state_space.clamp(&mut next);
        next
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn random_rollouts_are_as_long_as_a_typical_path() {
        // Unit square, steps of 0.1: E[max(|Δx|, |Δy|)] = 7/15 between two uniform points, so
        // a straight path takes about 5 steps (after rounding each path up to whole steps).
        let k = Kinematic::new(KinematicParams::default()).unwrap();
        assert!(
            (4..=6).contains(&k.rollout_length()),
            "{}",
            k.rollout_length()
        );
        // Half the speed, about twice the steps.
        let slow = Kinematic::new(KinematicParams {
            action_low: vec![-0.05, -0.05],
            action_high: vec![0.05, 0.05],
            ..KinematicParams::default()
        })
        .unwrap();
        let ratio = slow.rollout_length() as f64 / k.rollout_length() as f64;
        assert!((1.6..=2.4).contains(&ratio), "{ratio}");
    }

    #[test]
    fn model_adds_the_action_and_clips() {
        let k = Kinematic::new(KinematicParams::default()).unwrap();
        let p = k.predict(&[0.95, 0.5], &[0.1, -0.05]);
        assert!((p[0] - 1.0).abs() < 1e-12 && (p[1] - 0.45).abs() < 1e-12);
    }

    #[test]
    fn steering_respects_the_action_bounds() {
        let k = Kinematic::new(KinematicParams::default()).unwrap();
        let mut rng = rand::rng();
        let a = k.steer_toward(&[0.0, 0.0], &[1.0, 0.5], &mut rng);
        assert!((a[0] - 0.1).abs() < 1e-12 && (a[1] - 0.05).abs() < 1e-12);
    }

    #[test]
    fn obstacles_block_edges() {
        let params = KinematicParams {
            obstacles: vec![BoxObstacle {
                low: vec![0.4, 0.0],
                high: vec![0.45, 1.0],
            }],
            ..Default::default()
        };
        let k = Kinematic::new(params).unwrap();
        assert!(!k.edge_allowed(&[0.38, 0.5], &[0.1, 0.0], &[0.48, 0.5]));
        assert!(k.edge_allowed(&[0.2, 0.5], &[0.1, 0.0], &[0.3, 0.5]));
    }

    #[test]
    fn rejects_inconsistent_parameters() {
        let bad = KinematicParams {
            action_low: vec![0.1, -0.1],
            ..Default::default()
        };
        assert!(Kinematic::new(bad).is_err());
        let bad = KinematicParams {
            state_high: vec![1.0],
            ..Default::default()
        };
        assert!(Kinematic::new(bad).is_err());
    }
}
