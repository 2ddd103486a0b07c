//! An experiment's settings: the domain with its parameters, `d_max`, the seed, the MDE settings
//! and the learning settings. Requests give any subset; every omitted field takes the documented
//! default, and the resolved settings are what is stored and shown.
//!
//! These are the service's vocabulary (serde, validated once at the door); the numeric core gets
//! plain domain values built from them.

pub mod custom;
pub mod models;

pub use custom::{CustomSpec, DistanceSpec, FeaturesSpec, GoalSpec, ModelSpec, SpaceSpec};
pub use models::{DOMAIN_MODEL, NamedModelSpec};

use crate::domain::{
    BoxObstacle, DEFAULT_MAP, Domain, DomainError, GridFeatures, IcyGridworld, Kinematic,
    KinematicFeatures, KinematicParams, WaterPlant,
};
use crate::gp::{DEFAULT_INDUCING_POINTS, Kernel, NoiseMode};
use crate::limits::{
    MAX_BATCH_SIZE, MAX_CANDIDATES, MAX_EXPERT_SIZE, MAX_EXTENSIONS, MAX_INDUCING_POINTS,
    MAX_ITERATIONS, MAX_LEARNING_SCALE, MAX_NAME_LEN, MAX_PRIOR_MEAN, MAX_PROPOSAL_TTL_SECONDS,
    MAX_RESTARTS, MAX_SELECTION_SUBSET, MIN_EXPERT_SIZE, MIN_INDUCING_POINTS, MIN_SELECTION_SUBSET,
};
use crate::mde::{DEFAULT_EXPERT_SIZE, DEFAULT_SELECTION_SUBSET, EstimatorChoice};
use crate::planning::{
    AcquisitionKind, AcquisitionSettings, Aggregation, BetaSchedule, PlannerSettings,
    PlanningError, PlanningSettings, Strategy,
};
use crate::remote_model::{ModelCalls, ModelUrlPolicy};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// A setting that is not acceptable: which one (its path in the request, e.g.
/// `learning.gamma` or `domain.obstacles[2]`) and why.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field}: {reason}")]
pub struct InvalidSetting {
    /// Path of the setting in the request.
    pub field: String,
    /// What is wrong with it.
    pub reason: String,
}

impl InvalidSetting {
    /// The setting `field` is wrong because `reason`.
    pub fn new(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Self {
            field: field.into(),
            reason: reason.into(),
        }
    }
}

/// Which world, with its parameters. The tag is `kind`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum DomainSpec {
    /// The icy gridworld; `map` rows are strings of `.` (free), `#` (obstacle), `~` (ice), row
    /// `y` first-to-last, character `x` left-to-right. Default: the documented 12×12 map.
    IcyGridworld {
        /// The layout.
        #[serde(default = "default_map")]
        map: Vec<String>,
        /// How a state-action is fed to the MDE: `scaled` (the paper's `(x, y, dx, dy)`) or
        /// `per_move` (each move its own coordinates and length scales). Default `scaled`.
        #[serde(default)]
        features: GridFeatures,
    },
    /// The generic kinematic domain: `f̂(s, a) = clip(s + a)`.
    Kinematic {
        /// Lower state bounds (fixes the dimension). Default `[0, 0]`.
        #[serde(default = "kinematic_defaults::state_low")]
        state_low: Vec<f64>,
        /// Upper state bounds. Default `[1, 1]`.
        #[serde(default = "kinematic_defaults::state_high")]
        state_high: Vec<f64>,
        /// Lower action bounds (each ≤ 0). Default `[-0.1, -0.1]`.
        #[serde(default = "kinematic_defaults::action_low")]
        action_low: Vec<f64>,
        /// Upper action bounds (each ≥ 0). Default `[0.1, 0.1]`.
        #[serde(default = "kinematic_defaults::action_high")]
        action_high: Vec<f64>,
        /// Axis-aligned box obstacles for the approximate collision check. Default none.
        #[serde(default)]
        obstacles: Vec<ObstacleSpec>,
        /// Goal radius (Euclidean). Default 0.05.
        #[serde(default = "kinematic_defaults::goal_radius")]
        goal_radius: f64,
        /// What the MDE sees of a state-action: `state_action_prediction_length` (the state,
        /// the action, the model's prediction `clip(s + a)` and the length of the predicted
        /// move), `state_action_prediction` (without the length) or `state_action`. Default
        /// `state_action_prediction_length`; experiments keep the features they were created
        /// with (those created before the setting existed: `state_action`).
        #[serde(default)]
        features: KinematicFeatures,
    },
    /// The plant-watering world with its documented default scene (see
    /// `crates/precond-core/src/domain/water_plant/mod.rs`): pour one unit into the target without spilling more
    /// than 2 %, with leaves hanging over the target's opening.
    WaterPlant {},
    /// Any robot's own: its spaces, distance, goal test, obstacles and model (remote, linear or
    /// on the client); see [`CustomSpec`].
    Custom(Box<CustomSpec>),
}

/// The field at fault inside a tagged part of a body, and why: serde reads an internally tagged
/// enum (a `domain` of `kind: custom`) from a buffer, so its error names only the tagged part
/// (`domain`); reading `part` again as the variant's own type names the field
/// (`domain.goal.radius`). `path` is the tagged part's path in the body; `None` when `part` is
/// not one this can read again, or reads without error.
pub fn locate_in_tagged(path: &str, part: &serde_json::Value) -> Option<(String, String)> {
    if part.get("kind")?.as_str()? != "custom" {
        return None;
    }
    let mut inner = part.clone();
    inner.as_object_mut()?.remove("kind");
    let err = serde_path_to_error::deserialize::<_, CustomSpec>(inner).err()?;
    let at = err.path().to_string();
    let field = if at == "." {
        path.to_string()
    } else {
        format!("{path}.{at}")
    };
    Some((field, err.into_inner().to_string()))
}

/// An axis-aligned box.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ObstacleSpec {
    /// Lower corner.
    pub low: Vec<f64>,
    /// Upper corner.
    pub high: Vec<f64>,
}

fn default_map() -> Vec<String> {
    DEFAULT_MAP.iter().map(|r| r.to_string()).collect()
}

mod kinematic_defaults {
    use crate::domain::KinematicParams;
    pub fn state_low() -> Vec<f64> {
        KinematicParams::default().state_low
    }
    pub fn state_high() -> Vec<f64> {
        KinematicParams::default().state_high
    }
    pub fn action_low() -> Vec<f64> {
        KinematicParams::default().action_low
    }
    pub fn action_high() -> Vec<f64> {
        KinematicParams::default().action_high
    }
    pub fn goal_radius() -> f64 {
        KinematicParams::default().goal_radius
    }
}

impl Default for DomainSpec {
    fn default() -> Self {
        Self::IcyGridworld {
            map: default_map(),
            features: GridFeatures::default(),
        }
    }
}

impl DomainSpec {
    /// Builds the domain (a remote model called under `calls`' policy and limits); a failure
    /// names the parameter under `domain`.
    pub fn build(&self, calls: &Arc<ModelCalls>) -> Result<Arc<dyn Domain>, InvalidSetting> {
        let wrap = |e: DomainError| InvalidSetting::new(e.path_under("domain"), e.reason);
        Ok(match self {
            Self::IcyGridworld { map, features } => Arc::new(
                IcyGridworld::new(map)
                    .map_err(wrap)?
                    .with_features(*features),
            ),
            Self::Kinematic {
                state_low,
                state_high,
                action_low,
                action_high,
                obstacles,
                goal_radius,
                features,
            } => Arc::new(
                Kinematic::new(KinematicParams {
                    state_low: state_low.clone(),
                    state_high: state_high.clone(),
                    action_low: action_low.clone(),
                    action_high: action_high.clone(),
                    obstacles: obstacles
                        .iter()
                        .map(|o| BoxObstacle {
                            low: o.low.clone(),
                            high: o.high.clone(),
                        })
                        .collect(),
                    goal_radius: *goal_radius,
                    features: *features,
                })
                .map_err(wrap)?,
            ),
            Self::WaterPlant {} => Arc::new(WaterPlant::default()),
            Self::Custom(spec) => Arc::new(spec.build(calls)?),
        })
    }

    /// The kind of the domain's own model: a custom domain's `model.kind` (`remote`,
    /// `linear`, `client`), `built_in` for the built-in worlds'.
    pub fn model_kind(&self) -> &'static str {
        match self {
            Self::Custom(spec) => match spec.model {
                ModelSpec::Remote { .. } => "remote",
                ModelSpec::Linear { .. } => "linear",
                ModelSpec::Client {} => "client",
            },
            _ => "built_in",
        }
    }

    /// The state components that are angles (a custom domain's `state.periodic`; none for the
    /// built-in worlds).
    pub fn periodic(&self) -> Vec<usize> {
        match self {
            Self::Custom(spec) => spec.state.periodic.clone().unwrap_or_default(),
            _ => Vec::new(),
        }
    }

    /// The spec with every default filled in, checked against the operator's model URL
    /// policy (custom domains; the other kinds are resolved by serde's defaults).
    pub fn resolve(self, policy: &ModelUrlPolicy) -> Result<Self, InvalidSetting> {
        Ok(match self {
            Self::Custom(spec) => Self::Custom(Box::new(spec.resolve(policy)?)),
            other => other,
        })
    }
}

/// The model deviation estimator's settings as a client posts them: every field optional;
/// `label_cap` and `kernel` absent take the preset's (see [`MdeSettings`] for what each means).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct MdeRequest {
    /// [`MdeSettings::noise`]. Default `heteroscedastic`.
    pub noise: NoiseMode,
    /// [`MdeSettings::prior_mean`]. Default 0.
    #[schemars(range(min = -MAX_PRIOR_MEAN, max = MAX_PRIOR_MEAN))]
    pub prior_mean: f64,
    /// [`MdeSettings::restarts`]. Default 2.
    #[schemars(range(max = MAX_RESTARTS))]
    pub restarts: usize,
    /// [`MdeSettings::label_cap`]. Absent: the preset's (`default`: auto, `paper`: 0).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub label_cap: Option<LabelCap>,
    /// [`MdeSettings::kernel`]. Absent: the preset's (`default`: `auto`, `paper`:
    /// `matern52`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub kernel: Option<KernelChoice>,
    /// [`MdeSettings::estimator`]. Default `auto`.
    pub estimator: EstimatorChoice,
    /// [`MdeSettings::inducing_points`]. Default 256.
    #[schemars(range(min = MIN_INDUCING_POINTS, max = MAX_INDUCING_POINTS))]
    pub inducing_points: usize,
    /// [`MdeSettings::expert_size`]. Default 300.
    #[schemars(range(min = MIN_EXPERT_SIZE, max = MAX_EXPERT_SIZE))]
    pub expert_size: usize,
    /// [`MdeSettings::selection_subset`]. Default 1000.
    #[schemars(range(min = MIN_SELECTION_SUBSET, max = MAX_SELECTION_SUBSET))]
    pub selection_subset: usize,
    /// [`MdeSettings::reselect_every`]. Absent: the preset's (`default`: 5, `paper`: 1).
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 1, max = MAX_RESELECT_EVERY))]
    pub reselect_every: Option<usize>,
}

impl Default for MdeRequest {
    fn default() -> Self {
        Self {
            noise: NoiseMode::Heteroscedastic,
            prior_mean: 0.0,
            restarts: 2,
            label_cap: None,
            kernel: None,
            estimator: EstimatorChoice::Auto,
            inducing_points: DEFAULT_INDUCING_POINTS,
            expert_size: DEFAULT_EXPERT_SIZE,
            selection_subset: DEFAULT_SELECTION_SUBSET,
            reselect_every: None,
        }
    }
}

/// The model deviation estimator's settings, resolved: what an experiment fits with, as stored
/// and shown.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MdeSettings {
    /// Noise model: `heteroscedastic` or `homoscedastic`.
    pub noise: NoiseMode,
    /// Constant prior mean of the deviation (0 by default: unexplored regions look trustworthy
    /// but uncertain, which drives exploration); at most
    /// [`MAX_PRIOR_MEAN`] in magnitude.
    pub prior_mean: f64,
    /// Extra seeded optimiser starts beyond the first when fitting hyperparameters; at most 20.
    pub restarts: usize,
    /// How deviations become the labels the MDE is fitted on: clipped at `label_cap × d_max`
    /// (a number; `0` fits the raw labels, the paper's), or `"auto"`: at every fit, the cap
    /// (2 or 5 `d_max`, or raw) whose model judges its own training transitions best when each
    /// state-action is held out with all its copies (see
    /// [`crate::mde::fit_choosing_label_cap`]). Only whether a deviation is
    /// below `d_max` decides the precondition, so how far above it a failure lands is noise to
    /// the MDE: fitted raw, a few large deviations set the signal variance, and with it the
    /// uncertainty at every unseen point. A number is 0 or in `[1, 1000]`.
    pub label_cap: LabelCap,
    /// The GP's Matérn kernel: `matern12` (ν = 1/2, the exponential kernel), `matern32`,
    /// `matern52` (the paper's), or `auto`: at every fit, the one of the three whose fit has
    /// the highest log marginal likelihood on the data, unless another is clearly better held
    /// out (see [`KernelChoice`]).
    pub kernel: KernelChoice,
    /// The regressor fits use: `auto` (the exact GP up to 3000 transitions while its fit fits
    /// the server's memory budget, the sparse GP beyond), `exact`, `sparse` or `local_experts`
    /// (exact GPs on regions of the feature space, each with its own hyperparameters, see
    /// [`crate::mde::LocalExperts`]).
    pub estimator: EstimatorChoice,
    /// Inducing points of the sparse GP; 16 to 4096. With at most 1024 training transitions
    /// ([`crate::gp::DEFAULT_FULL_RANK_UP_TO`]) the sparse GP uses every training input
    /// instead, and is then the exact GP's fit in sparse form.
    pub inducing_points: usize,
    /// Transitions per expert the regions of `local_experts` aim at
    /// (`⌈n / expert_size⌉` regions); 50 to 3000. Unused by the other estimators.
    #[serde(default = "default_expert_size")]
    pub expert_size: usize,
    /// With the sparse GP, the kernel and the label cap are chosen by exact GPs on at most this
    /// many of the training transitions, evenly spaced (see
    /// [`crate::mde::fit_choosing_label_cap`]); 200 to 3000. Unused by the other estimators,
    /// which choose on every transition.
    #[serde(default = "default_selection_subset")]
    pub selection_subset: usize,
    /// How often a refit chooses the kernel and the label cap anew (1 ..= 1000): every
    /// `reselect_every`-th fit does, and so does a fit after the data doubled since the last
    /// choice or whose likelihood per transition fell; the fits between keep the last choice
    /// and start from the previous optimum (a warm refit: one fit instead of one per candidate,
    /// each from several starts). 1: every fit chooses from scratch, as before warm refits.
    pub reselect_every: usize,
}

/// `mde.expert_size` when a stored experiment's settings predate it.
fn default_expert_size() -> usize {
    DEFAULT_EXPERT_SIZE
}

/// `mde.selection_subset` when a stored experiment's settings predate it: the default, which
/// its next fit at scale then uses (the fixed 2,000 of before cost most of a fit on 100,000).
fn default_selection_subset() -> usize {
    DEFAULT_SELECTION_SUBSET
}

/// Largest `mde.reselect_every`.
pub const MAX_RESELECT_EVERY: usize = 1000;

/// A named set of defaults for the settings a preset decides (see [`LearningSettings::preset`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Preset {
    /// precond's defaults: the paper's method with the changes measured to learn more from the
    /// same executions (a label cap and a kernel chosen from the data, training proposals that
    /// relax β rather than give up, the `bottleneck` acquisition on a finite domain and
    /// `spread` on a continuous one).
    #[default]
    Default,
    /// The paper's exact configuration (raw labels, Matérn 5/2, no β relaxation, no batch
    /// diversity), kept as the baseline.
    Paper,
}

impl Preset {
    /// The label cap this preset uses when `mde.label_cap` is absent.
    pub fn label_cap(self) -> LabelCap {
        match self {
            Self::Default => LabelCap::Auto,
            Self::Paper => LabelCap::Fixed(0.0),
        }
    }

    /// How often this preset's refits choose the kernel and label cap anew when
    /// `mde.reselect_every` is absent: `default` every fifth fit (the others warm), `paper`
    /// every fit (each fit from scratch, as the paper's).
    pub fn reselect_every(self) -> usize {
        match self {
            Self::Default => 5,
            Self::Paper => 1,
        }
    }

    /// The kernel this preset uses when `mde.kernel` is absent.
    pub fn kernel(self) -> KernelChoice {
        match self {
            Self::Default => KernelChoice::Auto,
            Self::Paper => KernelChoice::Fixed(Kernel::Matern52),
        }
    }

    /// The acquisition function this preset uses when `learning.acquisition` is absent (see
    /// [`LearningSettings::acquisition`]), in a domain with finitely many state-actions
    /// (`finite`, the gridworld) or not.
    pub fn acquisition(self, finite: bool) -> AcquisitionKind {
        match self {
            // The measured best on gridworlds (docs/research/active-selection.md, "A probe to
            // the bottleneck"), and on the continuous worlds ("The spread acquisition").
            Self::Default if finite => AcquisitionKind::Bottleneck,
            Self::Default => AcquisitionKind::Spread,
            Self::Paper => AcquisitionKind::Lcb,
        }
    }

    /// Whether this preset relaxes β when a training problem has no plan (see
    /// [`LearningSettings::relax_beta`]).
    pub fn relax_beta(self) -> bool {
        self == Self::Default
    }

    /// How many first iterations this preset answers `active` with random rollouts (see
    /// [`LearningSettings::warmup_iterations`]): none in either. One random iteration gains
    /// per executed transition early on every world measured but costs the pusher and the
    /// gridworlds later (docs/research/active-selection.md, "Continuous worlds at equal
    /// cost").
    pub fn warmup_iterations(self) -> u32 {
        match self {
            Self::Default | Self::Paper => 0,
        }
    }

    /// Whether this preset's test plans use the β each fitted version certifies (see
    /// [`LearningSettings::calibrate_test_beta`]).
    pub fn calibrate_test_beta(self) -> bool {
        false
    }

    /// Whether this preset's test plans and default judgements judge each state-action at its
    /// locally calibrated β (see [`LearningSettings::local_test_margin`]): neither's.
    pub fn local_test_margin(self) -> bool {
        false
    }

    /// Whether this preset's `active` proposals score candidates with the σ of state-actions
    /// in flight fantasised as labelled (see [`LearningSettings::batch_diversity`]): neither's.
    /// The paper chose each trajectory of a batch from the model alone; `default` does too,
    /// because with it the seeded pusher test's plans crossed a step beyond `d_max` in 9 of 12
    /// seeds against 6 without (docs/research/active-selection.md, "Batch diversity").
    pub fn batch_diversity(self) -> bool {
        match self {
            Self::Default | Self::Paper => false,
        }
    }
}

/// Which Matérn kernel fits use (see [`MdeSettings::kernel`]). In JSON `"auto"` or a kernel's
/// name.
///
/// Where the model is wrong its deviation may jump (a leaf, a patch of ice, a wall, a contact)
/// or vary smoothly (an arm sagging under gravity, a puck sliding further on a wet floor). A
/// ν = 5/2 GP follows a jump only with length scales as short as the jump is sharp, so what it
/// learns spreads no further; the rough ν = 1/2 kernel follows a jump and keeps long length
/// scales, but explains a smooth deviation as rough and stays uncertain between data. `auto`
/// fits all three at the first candidate label cap and keeps the kernel whose fit has the
/// highest log marginal likelihood — the data's own evidence for each, on the same labels —
/// unless another judges the training state-actions clearly better held out
/// ([`best_kernel`](crate::mde::best_kernel)).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KernelChoice {
    /// Chosen at every fit among ν = 1/2, 3/2, 5/2 by the log marginal likelihood, or a
    /// clearly better held-out judgement.
    Auto,
    /// Always this kernel.
    Fixed(Kernel),
}

impl KernelChoice {
    /// The kernels a fit tries (one when fixed).
    pub fn candidates(self) -> Vec<Kernel> {
        match self {
            Self::Auto => Kernel::ALL.to_vec(),
            Self::Fixed(k) => vec![k],
        }
    }

    /// The setting's name: `auto` or the kernel's.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Fixed(k) => k.name(),
        }
    }
}

impl Serialize for KernelChoice {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.as_str())
    }
}

/// Written by hand like the serde impls: one of four names.
impl JsonSchema for KernelChoice {
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "KernelChoice".into()
    }

    fn json_schema(_: &mut schemars::SchemaGenerator) -> schemars::Schema {
        schemars::json_schema!({
            "type": "string",
            "enum": ["auto", "matern12", "matern32", "matern52"]
        })
    }
}

impl<'de> Deserialize<'de> for KernelChoice {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let name = String::deserialize(d)?;
        if name == "auto" {
            return Ok(Self::Auto);
        }
        Kernel::ALL
            .into_iter()
            .find(|k| k.name() == name)
            .map(Self::Fixed)
            .ok_or_else(|| {
                serde::de::Error::invalid_value(
                    serde::de::Unexpected::Str(&name),
                    &"\"auto\", \"matern12\", \"matern32\" or \"matern52\"",
                )
            })
    }
}

/// How deviations are capped before the MDE is fitted on them (see [`MdeSettings::label_cap`]).
/// In JSON a number (units of `d_max`; 0 = raw labels) or the string `"auto"`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LabelCap {
    /// Chosen at every fit from the data, among [`AUTO_LABEL_CAPS`] and raw labels.
    Auto,
    /// Clip at this many `d_max`; 0 = raw labels.
    Fixed(f64),
}

impl LabelCap {
    /// Checks a fixed cap: 0 (raw labels) or between 1 and 1000 (times `d_max`); the error
    /// lists what is accepted (`"0 (raw labels) or … got 0.5"`).
    pub fn check_fixed(cap: f64) -> Result<(), String> {
        if cap == 0.0 || (1.0..=1000.0).contains(&cap) {
            Ok(())
        } else {
            Err(format!(
                "0 (raw labels) or between 1 and 1000 (times d_max), got {cap}"
            ))
        }
    }
}

/// The caps (units of `d_max`) [`LabelCap::Auto`] tries beside raw labels: 2 makes the midpoint
/// between a safe and a failed neighbour `d_max`; 5 keeps gradual deviations up to half a
/// typical spill's size.
pub const AUTO_LABEL_CAPS: [f64; 2] = [2.0, 5.0];

impl Serialize for LabelCap {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            Self::Auto => s.serialize_str("auto"),
            Self::Fixed(cap) => s.serialize_f64(*cap),
        }
    }
}

/// Written by hand like the serde impls above: a number or the string `"auto"`.
impl JsonSchema for LabelCap {
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "LabelCap".into()
    }

    fn json_schema(_: &mut schemars::SchemaGenerator) -> schemars::Schema {
        schemars::json_schema!({
            "oneOf": [
                {"type": "number", "minimum": 0, "maximum": 1000},
                {"type": "string", "const": "auto"}
            ]
        })
    }
}

impl<'de> Deserialize<'de> for LabelCap {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl serde::de::Visitor<'_> for Visitor {
            type Value = LabelCap;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a number (times d_max; 0 = raw labels) or \"auto\"")
            }
            fn visit_f64<E: serde::de::Error>(self, v: f64) -> Result<LabelCap, E> {
                Ok(LabelCap::Fixed(v))
            }
            fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<LabelCap, E> {
                Ok(LabelCap::Fixed(v as f64))
            }
            fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<LabelCap, E> {
                Ok(LabelCap::Fixed(v as f64))
            }
            fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<LabelCap, E> {
                if v == "auto" {
                    Ok(LabelCap::Auto)
                } else {
                    Err(E::invalid_value(serde::de::Unexpected::Str(v), &self))
                }
            }
        }
        d.deserialize_any(Visitor)
    }
}

/// The active-learning settings as a client posts them: every field optional; `relax_beta`
/// absent takes the preset's (see [`LearningSettings`] for what each means).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct LearningRequest {
    /// [`LearningSettings::preset`]. Default `default`.
    pub preset: Preset,
    /// [`LearningSettings::strategy`]. Default `active`.
    pub strategy: Strategy,
    /// [`LearningSettings::batch_size`]. Default 5.
    #[schemars(range(min = 1, max = MAX_BATCH_SIZE))]
    pub batch_size: u32,
    /// [`LearningSettings::iterations`]. Default 20.
    #[schemars(range(min = 1, max = MAX_ITERATIONS))]
    pub iterations: u32,
    /// [`LearningSettings::n_candidates`]. Default 20.
    #[schemars(range(min = 1, max = MAX_CANDIDATES))]
    pub n_candidates: u32,
    /// [`LearningSettings::max_extensions`]. Default 5000.
    #[schemars(range(min = 1, max = MAX_EXTENSIONS))]
    pub max_extensions: u32,
    /// [`LearningSettings::c`]. Default 1.
    #[schemars(range(min = 0, max = MAX_LEARNING_SCALE))]
    pub c: f64,
    /// [`LearningSettings::gamma`]. Default 0.9.
    pub gamma: f64,
    /// [`LearningSettings::aggregation`]. Default `max`.
    pub aggregation: Aggregation,
    /// [`LearningSettings::acquisition`]. Absent: the preset's (`default`: `bottleneck` on a finite
    /// domain, `spread` elsewhere; `paper`: `lcb`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub acquisition: Option<AcquisitionKind>,
    /// [`LearningSettings::k1`]. Default 2.
    #[schemars(range(min = 0, max = MAX_LEARNING_SCALE))]
    pub k1: f64,
    /// [`LearningSettings::k2`]. Default 0.5.
    #[schemars(range(max = MAX_LEARNING_SCALE))]
    pub k2: f64,
    /// [`LearningSettings::test_beta`]. Default 2.
    #[schemars(range(min = -MAX_LEARNING_SCALE, max = MAX_LEARNING_SCALE))]
    pub test_beta: f64,
    /// [`LearningSettings::proposal_ttl_seconds`]. Default 600.
    #[schemars(range(min = 1, max = MAX_PROPOSAL_TTL_SECONDS))]
    pub proposal_ttl_seconds: u32,
    /// [`LearningSettings::relax_beta`]. Absent: the preset's (`default`: true, `paper`:
    /// false).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub relax_beta: Option<bool>,
    /// [`LearningSettings::batch_diversity`]. Absent: the preset's (false in both).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub batch_diversity: Option<bool>,
    /// [`LearningSettings::calibrate_test_beta`]. Absent: the preset's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub calibrate_test_beta: Option<bool>,
    /// [`LearningSettings::local_test_margin`]. Absent: the preset's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub local_test_margin: Option<bool>,
    /// [`LearningSettings::warmup_iterations`]. Absent: the preset's (0 in both).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub warmup_iterations: Option<u32>,
}

impl Default for LearningRequest {
    fn default() -> Self {
        Self {
            preset: Preset::Default,
            strategy: Strategy::Active,
            batch_size: 5,
            iterations: 20,
            n_candidates: 20,
            max_extensions: 5000,
            c: 1.0,
            gamma: 0.9,
            aggregation: Aggregation::Max,
            acquisition: None,
            k1: 2.0,
            k2: 0.5,
            test_beta: 2.0,
            proposal_ttl_seconds: 600,
            relax_beta: None,
            batch_diversity: None,
            calibrate_test_beta: None,
            local_test_margin: None,
            warmup_iterations: None,
        }
    }
}

/// The active-learning settings, resolved: what an experiment learns with, as stored and shown.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct LearningSettings {
    /// Where the settings it decides came from: `default` or `paper` (the paper's exact
    /// configuration).
    pub preset: Preset,
    /// Default strategy of proposals.
    pub strategy: Strategy,
    /// Executed trajectories per iteration; the MDE is refit after each batch.
    pub batch_size: u32,
    /// Planned iterations `J` of the β schedule.
    pub iterations: u32,
    /// Candidate trajectories per proposal.
    pub n_candidates: u32,
    /// RRT extension budget per search.
    pub max_extensions: u32,
    /// Exploration weight `c` in `α_step = μ − c σ`; `0 ..=`
    /// [`MAX_LEARNING_SCALE`].
    pub c: f64,
    /// Discount `γ` of the aggregation.
    pub gamma: f64,
    /// Aggregation `h` (of the `lcb` acquisition).
    pub aggregation: Aggregation,
    /// The acquisition function `active` minimises: `lcb` (the paper's `h(μ − c σ)`),
    /// `level_set` (the reach-weighted ambiguity of each step's side of `d_max`),
    /// `bottleneck` (the untrusted steps that would open the most sampled problems) or
    /// `spread` (the boundary uncertainty a candidate removes over the whole space; see
    /// [`AcquisitionKind`]).
    pub acquisition: AcquisitionKind,
    /// β schedule amplitude `k1`; `0 ..=` [`MAX_LEARNING_SCALE`].
    pub k1: f64,
    /// β schedule steepness `k2`; positive, at most
    /// [`MAX_LEARNING_SCALE`].
    pub k2: f64,
    /// β used by test-time plans (2: about 98 % confidence); at most
    /// [`MAX_LEARNING_SCALE`] in magnitude.
    pub test_beta: f64,
    /// Seconds an open proposal stays leased to its client.
    pub proposal_ttl_seconds: u32,
    /// When no training trajectory reaches the goal inside the precondition at the iteration's
    /// `β_j`, plan again at lower β down to `−k1` (see
    /// [`relaxation_ladder`](crate::planning::relaxation_ladder)) instead of answering
    /// `no_plan`: the robot tries the least doubtful way to a goal it cannot yet reach, so
    /// learning goes on where what is trusted ends (a passage the model doubts, after `β_j`
    /// turned positive). Test-time plans are never relaxed.
    pub relax_beta: bool,
    /// `active` proposals score their candidates as if the state-actions in flight — executed
    /// since the model was fitted, or planned by other clients' open proposals — were labelled
    /// already (their σ fantasised; trust is still judged by the model as fitted), so the
    /// trajectories of one batch do not chase one uncertainty. At most
    /// [`MAX_IN_FLIGHT`](crate::service::proposals::MAX_IN_FLIGHT) state-actions count.
    pub batch_diversity: bool,
    /// Test plans, and the precondition's default judgements, use the β the current model
    /// version certifies — the smallest β, at most `test_beta`, at which it trusts held out at
    /// most 2 % of its unsafe training transitions (see [`crate::mde::BetaChoice`]) — instead
    /// of `test_beta` itself. `test_beta` stays the bound, and the β until a version certifies
    /// one.
    pub calibrate_test_beta: bool,
    /// Test plans, and the precondition's default judgements, judge each state-action at its
    /// own β, calibrated locally ([`crate::mde::LocalMargin`]): the smallest β at which, among
    /// the training transitions near it that the current version trusts with their trajectory
    /// held out by less than half a σ's worth of β, at most 2 % are unsafe — or the test β
    /// (`test_beta`, or the certified one) where too few are near. Never above the test β.
    /// Experiments created before the setting have it off (migration 0026).
    pub local_test_margin: bool,
    /// During the first this many iterations an `active` proposal is a random rollout (what
    /// `random` answers: uniformly drawn actions inside the iteration's precondition) — an
    /// initial design spread over the space before the acquisition has a model worth
    /// following. The proposal says `random` as its strategy. `goal_conditioned` and `random`
    /// requests are unchanged. At most `iterations`.
    pub warmup_iterations: u32,
}

/// An experiment's settings as a client posts them; every field optional.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ExperimentRequest {
    /// Free-form name. Default `""`.
    #[serde(default)]
    #[schemars(length(max = MAX_NAME_LEN))]
    pub name: String,
    /// The domain. Default: the icy gridworld with its default map.
    #[serde(default)]
    pub domain: DomainSpec,
    /// Deviation tolerance. Default: the domain's (0.1 for the built-in worlds).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub d_max: Option<f64>,
    /// Seed of every random choice the service makes for this experiment. Default 0.
    #[serde(default)]
    pub seed: u64,
    /// MDE settings.
    #[serde(default)]
    pub mde: MdeRequest,
    /// Learning settings.
    #[serde(default)]
    pub learning: LearningRequest,
    /// Further models of the robot besides the domain's own (see [`models`]): each labels
    /// every posted transition with its own deviation. Default none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(max = models::MAX_MODELS))]
    pub models: Option<Vec<NamedModelSpec>>,
}

/// An experiment's fully resolved, validated settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ExperimentSettings {
    /// Free-form name.
    pub name: String,
    /// The domain.
    pub domain: DomainSpec,
    /// Deviation tolerance.
    pub d_max: f64,
    /// Seed.
    pub seed: u64,
    /// MDE settings.
    pub mde: MdeSettings,
    /// Learning settings.
    pub learning: LearningSettings,
    /// Further models of the robot besides the domain's own; left out when there are none,
    /// so that a single-model experiment's stored settings are as before they existed (never
    /// an empty list).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub models: Option<Vec<NamedModelSpec>>,
}

impl ExperimentSettings {
    /// The further models, in their order (none for a single-model experiment).
    pub fn further_models(&self) -> &[NamedModelSpec] {
        self.models.as_deref().unwrap_or_default()
    }

    /// The further models' names, in their order.
    pub fn further_model_names(&self) -> Vec<String> {
        self.further_models()
            .iter()
            .map(|m| m.name.clone())
            .collect()
    }

    /// Builds the further models over `domain` (no network: a remote model is first called
    /// when used, under `calls`' policy and limits).
    pub fn build_models(
        &self,
        domain: &dyn Domain,
        calls: &Arc<ModelCalls>,
    ) -> Result<Vec<crate::domain::NamedModel>, InvalidSetting> {
        models::build(
            self.further_models(),
            domain,
            &self.domain.periodic(),
            calls,
        )
    }
}

impl ExperimentRequest {
    /// Validates every field and resolves defaults (a remote model's URL against `calls`'
    /// policy). Returns the domain it built on the way.
    pub fn resolve(
        mut self,
        calls: &Arc<ModelCalls>,
    ) -> Result<(ExperimentSettings, Arc<dyn Domain>), InvalidSetting> {
        self.domain = self.domain.resolve(calls.policy())?;
        let domain = self.domain.build(calls)?;
        let models = models::resolve(
            self.models.take().unwrap_or_default(),
            &*domain,
            &self.domain.periodic(),
            calls,
            calls.policy(),
        )?;
        let models = (!models.is_empty()).then_some(models);
        if self.name.chars().count() > MAX_NAME_LEN {
            return Err(InvalidSetting::new(
                "name",
                format!("at most {MAX_NAME_LEN} characters"),
            ));
        }
        if let Some(why) = crate::limits::text_problem(&self.name) {
            return Err(InvalidSetting::new("name", why));
        }
        let d_max = self.d_max.unwrap_or_else(|| domain.default_d_max());
        positive("d_max", d_max)?;
        let cap = self
            .mde
            .label_cap
            .unwrap_or_else(|| self.learning.preset.label_cap());
        if let LabelCap::Fixed(cap) = cap {
            LabelCap::check_fixed(cap).map_err(|accepted| {
                InvalidSetting::new("mde.label_cap", format!("must be \"auto\", {accepted}"))
            })?;
        }
        let m = &self.mde;
        at_most("mde.prior_mean", m.prior_mean, MAX_PRIOR_MEAN)?;
        if m.restarts > MAX_RESTARTS {
            return Err(InvalidSetting::new(
                "mde.restarts",
                format!("at most {MAX_RESTARTS}"),
            ));
        }
        let mde = MdeSettings {
            noise: m.noise,
            prior_mean: m.prior_mean,
            restarts: m.restarts,
            label_cap: cap,
            kernel: m.kernel.unwrap_or_else(|| self.learning.preset.kernel()),
            estimator: m.estimator,
            inducing_points: m.inducing_points,
            expert_size: m.expert_size,
            selection_subset: m.selection_subset,
            reselect_every: m
                .reselect_every
                .unwrap_or_else(|| self.learning.preset.reselect_every()),
        };
        in_range(
            "mde.reselect_every",
            mde.reselect_every,
            1,
            MAX_RESELECT_EVERY,
        )?;
        in_range(
            "mde.inducing_points",
            mde.inducing_points,
            MIN_INDUCING_POINTS,
            MAX_INDUCING_POINTS,
        )?;
        in_range(
            "mde.expert_size",
            mde.expert_size,
            MIN_EXPERT_SIZE,
            MAX_EXPERT_SIZE,
        )?;
        in_range(
            "mde.selection_subset",
            mde.selection_subset,
            MIN_SELECTION_SUBSET,
            MAX_SELECTION_SUBSET,
        )?;
        let l = self.learning;
        in_range("learning.batch_size", l.batch_size, 1, MAX_BATCH_SIZE)?;
        in_range("learning.iterations", l.iterations, 1, MAX_ITERATIONS)?;
        in_range("learning.n_candidates", l.n_candidates, 1, MAX_CANDIDATES)?;
        in_range(
            "learning.max_extensions",
            l.max_extensions,
            1,
            MAX_EXTENSIONS,
        )?;
        in_range(
            "learning.proposal_ttl_seconds",
            l.proposal_ttl_seconds,
            1,
            MAX_PROPOSAL_TTL_SECONDS,
        )?;
        at_most("learning.c", l.c, MAX_LEARNING_SCALE)?;
        if l.c < 0.0 {
            return Err(InvalidSetting::new("learning.c", "must be ≥ 0"));
        }
        if !(l.gamma > 0.0 && l.gamma <= 1.0) {
            return Err(InvalidSetting::new("learning.gamma", "must be in (0, 1]"));
        }
        at_most("learning.k1", l.k1, MAX_LEARNING_SCALE)?;
        if l.k1 < 0.0 {
            return Err(InvalidSetting::new("learning.k1", "must be ≥ 0"));
        }
        positive("learning.k2", l.k2)?;
        at_most("learning.k2", l.k2, MAX_LEARNING_SCALE)?;
        at_most("learning.test_beta", l.test_beta, MAX_LEARNING_SCALE)?;
        let learning = LearningSettings {
            preset: l.preset,
            strategy: l.strategy,
            batch_size: l.batch_size,
            iterations: l.iterations,
            n_candidates: l.n_candidates,
            max_extensions: l.max_extensions,
            c: l.c,
            gamma: l.gamma,
            aggregation: l.aggregation,
            acquisition: l.acquisition.unwrap_or_else(|| {
                l.preset
                    .acquisition(domain.finite_state_actions().is_some())
            }),
            k1: l.k1,
            k2: l.k2,
            test_beta: l.test_beta,
            proposal_ttl_seconds: l.proposal_ttl_seconds,
            relax_beta: l.relax_beta.unwrap_or_else(|| l.preset.relax_beta()),
            batch_diversity: l
                .batch_diversity
                .unwrap_or_else(|| l.preset.batch_diversity()),
            calibrate_test_beta: l
                .calibrate_test_beta
                .unwrap_or_else(|| l.preset.calibrate_test_beta()),
            local_test_margin: l
                .local_test_margin
                .unwrap_or_else(|| l.preset.local_test_margin()),
            warmup_iterations: l
                .warmup_iterations
                .unwrap_or_else(|| l.preset.warmup_iterations()),
        };
        in_range(
            "learning.warmup_iterations",
            learning.warmup_iterations,
            0,
            learning.iterations,
        )?;
        learning.planning()?;
        Ok((
            ExperimentSettings {
                name: self.name,
                domain: self.domain,
                d_max,
                seed: self.seed,
                mde,
                learning,
                models,
            },
            domain,
        ))
    }
}

fn finite(field: &str, v: f64) -> Result<(), InvalidSetting> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(InvalidSetting::new(field, "must be a finite number"))
    }
}

/// A finite number of magnitude at most `max`; the error says the bound and why.
fn at_most(field: &str, v: f64, max: f64) -> Result<(), InvalidSetting> {
    finite(field, v)?;
    if v.abs() <= max {
        Ok(())
    } else {
        Err(InvalidSetting::new(
            field,
            format!(
                "must be at most {max:e} in magnitude, got {v:e} (larger values overflow the \
                 arithmetic they enter)"
            ),
        ))
    }
}

fn positive(field: &str, v: f64) -> Result<(), InvalidSetting> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(InvalidSetting::new(
            field,
            "must be a positive finite number",
        ))
    }
}

fn in_range<T: PartialOrd + Copy + std::fmt::Display>(
    field: &str,
    v: T,
    lo: T,
    hi: T,
) -> Result<(), InvalidSetting> {
    if (lo..=hi).contains(&v) {
        Ok(())
    } else {
        Err(InvalidSetting::new(
            field,
            format!("must be between {lo} and {hi}, got {v}"),
        ))
    }
}

impl ExperimentSettings {
    /// The label caps (units of `d_max`; 0 = raw labels) a fit tries: every candidate for
    /// `"auto"`, else the one fixed cap.
    pub fn label_caps(&self) -> Vec<f64> {
        match self.mde.label_cap {
            LabelCap::Auto => {
                let mut caps = AUTO_LABEL_CAPS.to_vec();
                caps.push(0.0);
                caps
            }
            LabelCap::Fixed(cap) => vec![cap],
        }
    }
}

impl LearningSettings {
    /// The βs a training proposal at `beta` tries in turn: `beta` alone, or its
    /// [`relaxation_ladder`](crate::planning::relaxation_ladder) down to `−k1`.
    pub fn training_betas(&self, beta: f64) -> Vec<f64> {
        if self.relax_beta {
            crate::planning::relaxation_ladder(beta, -self.k1)
        } else {
            vec![beta]
        }
    }

    /// The planner's and the acquisition's settings, checked; the error names the setting
    /// under `learning`.
    pub fn planning(&self) -> Result<PlanningSettings, InvalidSetting> {
        PlanningSettings::new(
            PlannerSettings {
                max_extensions: self.max_extensions as usize,
                n_candidates: self.n_candidates as usize,
                ..Default::default()
            },
            AcquisitionSettings {
                kind: self.acquisition,
                c: self.c,
                gamma: self.gamma,
                aggregation: self.aggregation,
                test_beta: self.test_beta,
            },
        )
        .map_err(|e| match e {
            PlanningError::InvalidSettings { field, reason } => {
                InvalidSetting::new(format!("learning.{field}"), reason)
            }
            other => InvalidSetting::new("learning", other.to_string()),
        })
    }

    /// The learning iteration after `n_trajectories` executed trajectories: the batches
    /// completed. The one place this is computed (the timeline's SQL groups trajectories the
    /// same way).
    pub fn iteration(&self, n_trajectories: i64) -> i64 {
        n_trajectories / i64::from(self.batch_size.max(1))
    }

    /// The β schedule over the planned iterations.
    pub fn beta_schedule(&self) -> BetaSchedule {
        BetaSchedule {
            k1: self.k1,
            k2: self.k2,
            iterations: self.iterations as usize,
        }
    }

    /// The strategy that answers a training proposal asking for `requested` (default
    /// [`strategy`](Self::strategy)) in `iteration`: `random` for `active` during the
    /// [`warmup_iterations`](Self::warmup_iterations), else what was asked.
    pub fn answering_strategy(&self, requested: Option<Strategy>, iteration: i64) -> Strategy {
        let strategy = requested.unwrap_or(self.strategy);
        if strategy == Strategy::Active && iteration < i64::from(self.warmup_iterations) {
            Strategy::Random
        } else {
            strategy
        }
    }

    /// `β_j` of the schedule at iteration `j` (`j < 0` counts as 0).
    pub fn training_beta(&self, iteration: i64) -> f64 {
        self.beta_schedule().beta(iteration.max(0) as usize)
    }
}
