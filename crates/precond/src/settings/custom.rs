//! The settings of a client-declared (`custom`) domain: the robot's spaces, the MDE's
//! components, the distance, the goal test, obstacles, and where its model `f̂` lives.
//!
//! ```json
//! {"kind": "custom",
//!  "state":  {"names": ["x", "y"], "low": [0, 0], "high": [1, 1]},
//!  "action": {"names": ["dx", "dy"], "low": [-0.1, -0.1], "high": [0.1, 0.1]},
//!  "features": {"state": [0, 1], "action": [0, 1], "action_length": true},
//!  "distance": {"weights": [1, 1]},
//!  "goal": {"components": [0, 1], "radius": 0.05},
//!  "obstacles": [{"low": [0.4, 0], "high": [0.5, 0.6]}],
//!  "model": {"kind": "remote", "url": "http://robot-pc:9000/predict", "timeout_ms": 2000}}
//! ```
//!
//! Omitted parts resolve to their defaults (every component feeds the MDE, unit weights, the
//! goal on every state component with radius 0.05) and the resolved settings show them.

use super::{InvalidSetting, ObstacleSpec};
use crate::domain::custom::{MAX_ACTION_VALUES, MAX_DIM};
use crate::domain::{
    BoxObstacle, ClientModel, CustomDomain, CustomParams, DomainError, DynamicsModel, LinearModel,
    Space,
};
use crate::remote_model::{MAX_TIMEOUT_MS, ModelCalls, ModelUrlPolicy, RemoteModel};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// A state or action space as declared.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct SpaceSpec {
    /// One name per component. Default `s0, s1, …` / `a0, a1, …`.
    #[serde(default)]
    pub names: Vec<String>,
    /// Lower bounds. For a discrete action space, default: the smallest value per component.
    #[serde(default)]
    pub low: Vec<f64>,
    /// Upper bounds. For a discrete action space, default: the largest value per component.
    #[serde(default)]
    pub high: Vec<f64>,
    /// The allowed actions of a discrete action space.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(min = 1, max = MAX_ACTION_VALUES))]
    pub values: Option<Vec<Vec<f64>>>,
    /// Components that are angles (a heading, a continuous joint), by index, their period
    /// `high − low` (e.g. bounds `[−π, π]`): distances, the goal test, steering and the MDE's
    /// features take the shorter way round, and the service wraps its model's predictions into
    /// the bounds. State components only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub periodic: Option<Vec<usize>>,
}

/// Which components feed the MDE.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct FeaturesSpec {
    /// State components, by index.
    #[serde(default)]
    pub state: Vec<usize>,
    /// Action components, by index.
    #[serde(default)]
    pub action: Vec<usize>,
    /// Whether one more feature follows: the length of those action components, each over the
    /// largest magnitude its bounds allow (root mean square, in `[0, 1]`). Default: `true`
    /// when `action` lists a component (experiments stored before it existed: `false`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub action_length: Option<bool>,
    /// Components of the model's prediction `ŝ' = f̂(s, a)` fed to the MDE after them, by index,
    /// each scaled to the unit box by the state's bounds: where a move ends, which decides most
    /// of what a model ignores (a contact, a slope, a slippery patch). Default: every state
    /// component for a remote or linear model, none for a client-side one (whose queries would
    /// then have to carry `s_pred`); experiments stored before it existed: none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub prediction: Option<Vec<usize>>,
    /// Whether one more feature ends them: the length of the predicted move in the domain's
    /// distance, over the state box's diagonal (in `[0, 1]`). Defaults as `prediction`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub move_length: Option<bool>,
}

/// Whether a custom domain's features end with the action's length unless the request says
/// ([`FeaturesSpec::action_length`]).
pub const DEFAULT_ACTION_LENGTH: bool = true;

/// The weighted Euclidean distance `d = sqrt(Σ w_i (ŝ_i − s_i)²)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct DistanceSpec {
    /// One weight ≥ 0 per state component, not all 0.
    pub weights: Vec<f64>,
}

/// The goal test: the chosen state components within `radius` of the goal.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct GoalSpec {
    /// State components compared with the goal vector. Default: all.
    #[serde(default)]
    pub components: Option<Vec<usize>>,
    /// A Euclidean radius on those components, or one radius per component (metres and
    /// radians alike need their own). Default 0.05.
    #[serde(default = "default_goal_radius")]
    pub radius: GoalRadius,
}

/// A goal's radius: one for every component (a ball), or one per component (an ellipsoid:
/// `Σ ((s_i − g_i) / r_i)² ≤ 1`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(
    untagged,
    expecting = "must be a number, or an array of one number per goal component"
)]
pub enum GoalRadius {
    /// One Euclidean radius.
    One(f64),
    /// One radius per goal component, in its units.
    Each(Vec<f64>),
}

/// Written by hand to say what validation requires: every radius positive, at least one.
impl JsonSchema for GoalRadius {
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "GoalRadius".into()
    }

    fn json_schema(_: &mut schemars::SchemaGenerator) -> schemars::Schema {
        schemars::json_schema!({
            "anyOf": [
                {"type": "number", "exclusiveMinimum": 0},
                {
                    "type": "array",
                    "minItems": 1,
                    "items": {"type": "number", "exclusiveMinimum": 0}
                }
            ]
        })
    }
}

fn default_goal_radius() -> GoalRadius {
    GoalRadius::One(0.05)
}

impl Default for GoalSpec {
    fn default() -> Self {
        Self {
            components: None,
            radius: default_goal_radius(),
        }
    }
}

/// Where the model `f̂` lives. The tag is `kind`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum ModelSpec {
    /// Served by the robot's own process: `POST url {"states", "actions"} → {"next_states",
    /// "valid"?}` (only under URL prefixes the operator allows).
    Remote {
        /// The model's URL (`http://…`), stored as normalised when checked (what is called).
        #[schemars(length(max = crate::remote_model::policy::MAX_URL_LEN))]
        url: String,
        /// Time limit of one call, in milliseconds. Default 2000; the operator's
        /// `--max-model-timeout-ms` caps it.
        #[serde(default = "default_timeout_ms")]
        #[schemars(range(min = 1, max = MAX_TIMEOUT_MS))]
        timeout_ms: u64,
    },
    /// `ŝ' = clip(A s + B a + c)` to the state bounds.
    Linear {
        /// `A`, n × n.
        #[serde(rename = "A")]
        a: Vec<Vec<f64>>,
        /// `B`, n × m.
        #[serde(rename = "B")]
        b: Vec<Vec<f64>>,
        /// `c`, n. Default zeros.
        #[serde(default)]
        c: Option<Vec<f64>>,
    },
    /// The client's own: it posts `s_pred` with every transition and plans itself, posting
    /// candidate trajectories for the service to score.
    Client {},
}

pub(super) fn default_timeout_ms() -> u64 {
    2000
}

impl ModelSpec {
    /// Fills in the defaults of a model of an `n`-dimensional state (a linear model's `c`)
    /// and checks a remote model's time limit and URL against `policy`, storing the URL in
    /// the normalised form that was checked and will be called. Errors name the field under
    /// `at` (e.g. `domain.model`).
    pub fn resolve(
        &mut self,
        n: usize,
        policy: &ModelUrlPolicy,
        at: &str,
    ) -> Result<(), InvalidSetting> {
        match self {
            ModelSpec::Remote { url, timeout_ms } => {
                if !(1..=MAX_TIMEOUT_MS).contains(timeout_ms) {
                    return Err(InvalidSetting::new(
                        format!("{at}.timeout_ms"),
                        format!("must be between 1 and {MAX_TIMEOUT_MS}"),
                    ));
                }
                *url = policy
                    .normalise(url)
                    .map_err(|reason| InvalidSetting::new(format!("{at}.url"), reason))?;
            }
            ModelSpec::Linear { c, .. } => {
                c.get_or_insert_with(|| vec![0.0; n]);
            }
            ModelSpec::Client {} => {}
        }
        Ok(())
    }

    /// Builds the model over the spaces `state` and `action` (no network: a remote model is
    /// first called when used, under `calls`' policy and limits); `periodic` are the state's
    /// angle components, into whose bounds a linear model wraps its predictions. Errors name
    /// the field under `at`.
    pub fn build(
        &self,
        state: &Space,
        action: &Space,
        periodic: &[usize],
        calls: &Arc<ModelCalls>,
        at: &str,
    ) -> Result<Arc<dyn DynamicsModel>, InvalidSetting> {
        Ok(match self {
            ModelSpec::Remote { url, timeout_ms } => Arc::new(RemoteModel::new(
                url,
                *timeout_ms,
                state.dim(),
                calls.clone(),
            )),
            ModelSpec::Linear { a, b, c } => {
                let c = c.clone().unwrap_or_else(|| vec![0.0; state.dim()]);
                Arc::new(
                    LinearModel::new(a.clone(), b.clone(), c, state, action)
                        .map_err(|e| InvalidSetting::new(e.path_under(at), e.reason))?
                        .with_periodic(periodic),
                )
            }
            ModelSpec::Client {} => Arc::new(ClientModel),
        })
    }
}

/// A client-declared domain as posted (see the module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct CustomSpec {
    /// The state space (continuous, bounded).
    pub state: SpaceSpec,
    /// The action space: bounds, or `values` for a discrete one.
    pub action: SpaceSpec,
    /// Components fed to the MDE. Default: all.
    #[serde(default)]
    pub features: Option<FeaturesSpec>,
    /// The distance. Default: unit weights.
    #[serde(default)]
    pub distance: Option<DistanceSpec>,
    /// The goal test. Default: every state component, radius 0.05.
    #[serde(default)]
    pub goal: GoalSpec,
    /// Boxes in the state space that planned edges may not pass through. Default none.
    #[serde(default)]
    #[schemars(length(max = crate::domain::custom::MAX_OBSTACLES))]
    pub obstacles: Vec<ObstacleSpec>,
    /// Where the model lives.
    pub model: ModelSpec,
    /// Actions the planner samples per steering step (continuous actions). Default 8.
    #[serde(default = "default_steer_samples")]
    #[schemars(range(min = 1, max = crate::domain::custom::MAX_STEER_SAMPLES))]
    pub steer_samples: usize,
    /// Steps of a `random`-strategy rollout. Absent: as long as a goal-reaching plan for the
    /// same problem (one RRT run at the proposal's β), or 20 when the planner finds none — so
    /// that `random` executes about as much per trajectory as the goal-conditioned strategies.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 1, max = crate::domain::custom::MAX_ROLLOUT_LENGTH))]
    pub rollout_length: Option<usize>,
}

fn default_steer_samples() -> usize {
    8
}

fn invalid(e: DomainError) -> InvalidSetting {
    InvalidSetting::new(e.path_under("domain"), e.reason)
}

fn bad(field: &str, reason: impl Into<String>) -> InvalidSetting {
    InvalidSetting::new(format!("domain.{field}"), reason)
}

impl SpaceSpec {
    /// Fills in default names and the bounds of a discrete space.
    fn resolve(mut self, what: &str, prefix: &str) -> Result<Self, InvalidSetting> {
        if let Some(values) = &self.values {
            if values.is_empty() || values.len() > MAX_ACTION_VALUES {
                return Err(bad(
                    &format!("{what}.values"),
                    format!("must hold 1 to {MAX_ACTION_VALUES} actions"),
                ));
            }
            let m = values[0].len();
            if m == 0 || m > MAX_DIM {
                return Err(bad(
                    &format!("{what}.values[0]"),
                    format!("the dimension must be between 1 and {MAX_DIM}"),
                ));
            }
            for (k, v) in values.iter().enumerate() {
                if v.len() != m {
                    return Err(bad(
                        &format!("{what}.values[{k}]"),
                        format!("expected {m} components like values[0], got {}", v.len()),
                    ));
                }
                if v.iter().any(|x| !x.is_finite()) {
                    return Err(bad(
                        &format!("{what}.values[{k}]"),
                        "must be finite numbers",
                    ));
                }
            }
            let fold = |f: fn(f64, f64) -> f64, init: f64| -> Vec<f64> {
                (0..m)
                    .map(|i| values.iter().map(|v| v[i]).fold(init, f))
                    .collect()
            };
            if self.low.is_empty() {
                self.low = fold(f64::min, f64::INFINITY);
            }
            if self.high.is_empty() {
                self.high = fold(f64::max, f64::NEG_INFINITY);
            }
        }
        let n = if self.names.is_empty() {
            self.low.len()
        } else {
            self.names.len()
        };
        if n == 0 {
            return Err(bad(
                &format!("{what}.low"),
                "give the bounds (and optionally names) of every component",
            ));
        }
        if self.names.is_empty() {
            self.names = (0..n).map(|i| format!("{prefix}{i}")).collect();
        }
        if let Some(k) = self.names.iter().position(|s| s.is_empty() || s.len() > 64) {
            return Err(bad(
                &format!("{what}.names[{k}]"),
                "must be 1 to 64 characters",
            ));
        }
        for (k, name) in self.names.iter().enumerate() {
            if let Some(why) = crate::limits::text_problem(name) {
                return Err(bad(&format!("{what}.names[{k}]"), why));
            }
        }
        Ok(self)
    }

    fn space(&self) -> Space {
        Space {
            names: self.names.clone(),
            low: self.low.clone(),
            high: self.high.clone(),
            values: self.values.clone(),
        }
    }
}

impl CustomSpec {
    /// Fills in every default so that the stored and shown settings say exactly what is used,
    /// and checks that a remote model's URL is one the operator allows, storing it in the
    /// normalised form that was checked and will be called.
    pub fn resolve(mut self, policy: &ModelUrlPolicy) -> Result<Self, InvalidSetting> {
        self.state = self.state.resolve("state", "s")?;
        self.action = self.action.resolve("action", "a")?;
        let (n, m) = (self.state.names.len(), self.action.names.len());
        if self.action.periodic.as_ref().is_some_and(|p| !p.is_empty()) {
            return Err(bad(
                "action.periodic",
                "only state components can be periodic (an action is a command, not a pose)",
            ));
        }
        let periodic = self.state.periodic.as_deref().unwrap_or_default();
        if periodic.len() > n {
            // Checked first: the test for repeats below is quadratic in the list's length.
            return Err(bad(
                "state.periodic",
                format!("at most {n} components (the state has {n})"),
            ));
        }
        for (k, i) in periodic.iter().enumerate() {
            if periodic[..k].contains(i) {
                return Err(bad(
                    &format!("state.periodic[{k}]"),
                    format!("component {i} is listed twice"),
                ));
            }
        }
        let features = self.features.get_or_insert_with(|| FeaturesSpec {
            state: (0..n).collect(),
            action: (0..m).collect(),
            action_length: None,
            prediction: None,
            move_length: None,
        });
        features
            .action_length
            .get_or_insert(DEFAULT_ACTION_LENGTH && !features.action.is_empty());
        // The model's prediction, where the service can ask for it itself.
        let served = !matches!(self.model, ModelSpec::Client {});
        features
            .prediction
            .get_or_insert_with(|| if served { (0..n).collect() } else { Vec::new() });
        features.move_length.get_or_insert(served);
        self.distance.get_or_insert_with(|| DistanceSpec {
            weights: vec![1.0; n],
        });
        self.goal.components.get_or_insert_with(|| (0..n).collect());
        self.model.resolve(n, policy, "domain.model")?;
        Ok(self)
    }

    /// Builds the domain with its model (no network: a remote model is first called when
    /// used, under `calls`' policy and limits). Errors name the parameter under `domain`.
    pub fn build(&self, calls: &Arc<ModelCalls>) -> Result<CustomDomain, InvalidSetting> {
        let (state, action) = (self.state.space(), self.action.space());
        let periodic = self.state.periodic.as_deref().unwrap_or_default();
        let model = self
            .model
            .build(&state, &action, periodic, calls, "domain.model")?;
        let (n, m) = (state.dim(), action.dim());
        let features = self.features.clone().unwrap_or(FeaturesSpec {
            state: (0..n).collect(),
            action: (0..m).collect(),
            action_length: None,
            prediction: None,
            move_length: None,
        });
        let params = CustomParams {
            state,
            periodic: self.state.periodic.clone().unwrap_or_default(),
            action,
            feature_state: features.state,
            feature_action: features.action,
            // Resolved settings always say (stored ones since migrations 0017 and 0024).
            action_length: features.action_length.unwrap_or(false),
            feature_prediction: features.prediction.unwrap_or_default(),
            move_length: features.move_length.unwrap_or(false),
            weights: self
                .distance
                .as_ref()
                .map_or_else(|| vec![1.0; n], |d| d.weights.clone()),
            goal_components: self
                .goal
                .components
                .clone()
                .unwrap_or_else(|| (0..n).collect()),
            goal_radius: match &self.goal.radius {
                GoalRadius::One(r) => vec![*r],
                GoalRadius::Each(radii) => radii.clone(),
            },
            obstacles: self
                .obstacles
                .iter()
                .map(|o| BoxObstacle {
                    low: o.low.clone(),
                    high: o.high.clone(),
                })
                .collect(),
            steer_samples: self.steer_samples,
            rollout_length: self.rollout_length,
        };
        CustomDomain::new(params, model).map_err(invalid)
    }
}
