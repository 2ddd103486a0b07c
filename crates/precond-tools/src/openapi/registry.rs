//! Which Rust type each schema of `components/schemas` is generated from.

use schemars::JsonSchema;
use schemars::generate::SchemaSettings;
use serde_json::Value;
use std::borrow::Cow;

use precond::api;
use precond::domain::{FeatureMap, Transition};
use precond::gp::{GpPredictor, Hyperparameters, NoisePredictor, NoiseSummary, Predictor};
use precond::mde::{BetaChoice, ExpertsPredictor, HeldOutTrust, Judgement, KernelTrial};
use precond::settings::{
    DomainSpec, ExperimentRequest, FeaturesSpec, GoalSpec, LearningRequest, LearningSettings,
    MdeRequest, MdeSettings, ModelSpec, ObstacleSpec, SpaceSpec,
};

/// Which side of the wire a schema describes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Side {
    /// The server writes it: generated for serialisation (a property is required when the
    /// server always emits it, an `Option` it does not skip included).
    Response,
    /// The server reads it: generated for deserialisation (a property is required when the
    /// server refuses a body without it).
    Request,
}

/// One Rust type shared by two routes whose bodies differ by properties the server sets on one
/// route only (a property skipped when `None`, always `Some` on one route, always `None` on the
/// other): what the schema of this route says of them, at a property path (`""`: the body).
#[derive(Clone, Copy, Debug)]
pub enum Adjust {
    /// Always emitted (never `null`) on this route.
    Require(&'static str, &'static [&'static str]),
    /// Never emitted on this route.
    Omit(&'static str, &'static [&'static str]),
}

/// A schema of the document and the Rust type it is generated from.
pub struct Entry {
    /// The schema's name in `components/schemas`.
    pub schema: &'static str,
    /// The side of the wire it describes.
    pub side: Side,
    /// The Rust type's path (`precond::api::ExperimentResponse`).
    pub rust: fn() -> &'static str,
    /// The name schemars gives the type (its `$defs` key where another type embeds it).
    pub rust_name: fn() -> Cow<'static, str>,
    /// The type's JSON Schema (draft 2020-12) for that side, as schemars generates it.
    pub generate: fn(Side) -> Value,
    /// What this route's body says differently from the type.
    pub adjust: &'static [Adjust],
}

const fn entry<T: JsonSchema>(schema: &'static str, side: Side) -> Entry {
    Entry {
        schema,
        side,
        rust: std::any::type_name::<T>,
        rust_name: T::schema_name,
        generate: rust_schema::<T>,
        adjust: &[],
    }
}

const fn adjusted<T: JsonSchema>(
    schema: &'static str,
    side: Side,
    adjust: &'static [Adjust],
) -> Entry {
    Entry {
        adjust,
        ..entry::<T>(schema, side)
    }
}

/// A type's JSON Schema for one side of the wire.
pub fn rust_schema<T: JsonSchema>(side: Side) -> Value {
    let settings = SchemaSettings::draft2020_12();
    let settings = match side {
        Side::Response => settings.for_serialize(),
        Side::Request => settings.for_deserialize(),
    };
    settings
        .into_generator()
        .into_root_schema_for::<T>()
        .to_value()
}

use Side::{Request, Response};

/// Every schema generated from a Rust type of its own, and that type. A type may describe
/// several schemas (a request and a response; two routes, told apart by [`Adjust`]); a schema
/// named twice (one for each side) is generated from its first entry and checked against both.
pub const ENTRIES: &[Entry] = &[
    // errors (`details` is a JSON value built per code in crates/precond/src/http/error.rs)
    entry::<api::ErrorBody>("Error", Response),
    entry::<api::ErrorDetail>("ErrorBody", Response),
    // health
    entry::<api::HealthResponse>("Health", Response),
    entry::<api::HealthResponse>("Readiness", Response),
    // spaces and domains
    entry::<api::SpaceView>("Space", Response),
    entry::<DomainSpec>("DomainSpec", Request),
    entry::<DomainSpec>("ResolvedDomainSpec", Response),
    entry::<ObstacleSpec>("Obstacle", Request),
    entry::<ObstacleSpec>("Obstacle", Response),
    entry::<SpaceSpec>("SpaceSpec", Request),
    entry::<SpaceSpec>("ResolvedSpaceSpec", Response),
    entry::<FeaturesSpec>("FeaturesSpec", Request),
    entry::<FeaturesSpec>("ResolvedFeaturesSpec", Response),
    entry::<GoalSpec>("GoalSpec", Request),
    entry::<GoalSpec>("ResolvedGoalSpec", Response),
    entry::<ModelSpec>("ModelSpec", Request),
    entry::<ModelSpec>("ResolvedModelSpec", Response),
    // settings
    entry::<MdeRequest>("MdeSettings", Request),
    entry::<LearningRequest>("LearningSettings", Request),
    entry::<MdeSettings>("ResolvedMdeSettings", Response),
    entry::<LearningSettings>("ResolvedLearningSettings", Response),
    // experiments
    entry::<ExperimentRequest>("ExperimentRequest", Request),
    entry::<api::ExperimentResponse>("Experiment", Response),
    entry::<api::ExperimentList>("ExperimentList", Response),
    // trajectories
    entry::<Transition>("TransitionRequest", Request),
    entry::<api::TrajectoryRequest>("TrajectoryRequest", Request),
    entry::<api::TrajectorySource>("TrajectorySource", Request),
    entry::<api::TrajectorySource>("ResolvedTrajectorySource", Response),
    entry::<api::TrajectoryCreated>("TrajectoryCreated", Response),
    entry::<api::TransitionView>("Transition", Response),
    entry::<api::TrajectoryResponse>("Trajectory", Response),
    entry::<api::TransitionPage>("TransitionPage", Response),
    entry::<precond::import::ImportReport>("ImportReport", Response),
    entry::<precond::import::ImportStop>("ImportStop", Response),
    // dashboard reads
    entry::<api::RunView>("Run", Response),
    entry::<api::ExclusionRequest>("ExclusionRequest", Request),
    entry::<api::ExclusionView>("Exclusion", Response),
    entry::<api::ExclusionPage>("ExclusionPage", Response),
    entry::<api::RunPage>("RunPage", Response),
    entry::<api::TimelineIteration>("TimelineIteration", Response),
    entry::<api::TimelineModel>("TimelineModel", Response),
    entry::<api::Timeline>("Timeline", Response),
    entry::<api::ModelLabels>("ModelLabels", Response),
    entry::<api::MapAxis>("MapAxis", Response),
    entry::<api::MapPoint>("MapPoint", Response),
    entry::<api::PreconditionMap>("PreconditionMap", Response),
    entry::<api::Coverage>("Coverage", Response),
    entry::<api::PreconditionRates>("PreconditionRates", Response),
    entry::<api::Diagnostics>("Diagnostics", Response),
    // model
    entry::<Hyperparameters>("Hyperparameters", Response),
    entry::<NoiseSummary>("NoiseSummary", Response),
    entry::<api::ModelResponse>("Model", Response),
    entry::<HeldOutTrust>("HeldOutTrust", Response),
    entry::<api::FitRefusalView>("FitRefusal", Response),
    entry::<KernelTrial>("KernelTrial", Response),
    entry::<BetaChoice>("BetaChoice", Response),
    entry::<api::ModelExport>("ModelExport", Response),
    entry::<FeatureMap>("FeatureMap", Response),
    entry::<Predictor>("Predictor", Response),
    entry::<ExpertsPredictor>("ExpertsPredictor", Response),
    entry::<GpPredictor>("GpPredictor", Response),
    entry::<NoisePredictor>("NoisePredictor", Response),
    entry::<api::RejectionCounts>("RejectionCounts", Response),
    // precondition
    entry::<api::Point>("PointRequest", Request),
    entry::<api::PreconditionRequest>("PreconditionRequest", Request),
    entry::<Judgement>("PreconditionResult", Response),
    // `POST …/precondition` answers without the point, `GET …/precondition` with it.
    adjusted::<api::PreconditionResponse>(
        "PreconditionAnswer",
        Response,
        &[Adjust::Omit("", &["s", "a"])],
    ),
    adjusted::<api::PreconditionResponse>(
        "PointPreconditionAnswer",
        Response,
        &[Adjust::Require("", &["s", "a"])],
    ),
    // planning
    entry::<api::ProposalRequest>("ProposalRequest", Request),
    entry::<api::CandidateTrajectory>("CandidateTrajectory", Request),
    entry::<api::ContinueRequest>("ContinueRequest", Request),
    entry::<api::ContinueResponse>("ContinueResponse", Response),
    // A plan's trajectory has no acquisition values; a proposal's always has them.
    adjusted::<api::PlannedTrajectory>(
        "PlannedTrajectory",
        Response,
        &[Adjust::Omit("", &["alpha_step", "alpha"])],
    ),
    adjusted::<api::PlannedTrajectory>(
        "ProposedTrajectory",
        Response,
        &[Adjust::Require("", &["alpha_step", "alpha"])],
    ),
    entry::<api::CandidateView>("CandidateScore", Response),
    entry::<api::ProposalResponse>("Proposal", Response),
    entry::<api::PlanRequest>("PlanRequest", Request),
    entry::<api::PlanResponse>("Plan", Response),
    // types embedded in the bodies above, named in the document
    entry::<precond::settings::NamedModelSpec>("NamedModelSpec", Request),
    entry::<precond::settings::NamedModelSpec>("ResolvedNamedModelSpec", Response),
    entry::<precond::records::ModelLabel>("ModelLabel", Response),
    entry::<api::ModelLabelStats>("ModelLabelStats", Response),
    entry::<api::ModelCalls>("ModelCalls", Response),
    entry::<precond::mde::SelectionRecord>("SelectionRecord", Response),
    entry::<precond::mde::FitPhase>("FitPhase", Response),
];

/// Where a type describes several schemas of one side, which one a property of another schema
/// refers to: `(schema, property, the schema it refers to)`.
pub const CONTEXTS: &[(&str, &str, &str)] = &[
    ("Proposal", "trajectory", "ProposedTrajectory"),
    ("Plan", "trajectory", "PlannedTrajectory"),
];

/// The variants of a tagged union that the document names, each a schema of its own:
/// `(union schema, tag value, variant schema)`.
pub const VARIANTS: &[(&str, &str, &str)] = &[
    ("DomainSpec", "icy_gridworld", "IcyGridworldSpec"),
    ("DomainSpec", "kinematic", "KinematicSpec"),
    ("DomainSpec", "water_plant", "WaterPlantSpec"),
    ("DomainSpec", "custom", "CustomSpec"),
    (
        "ResolvedDomainSpec",
        "icy_gridworld",
        "ResolvedIcyGridworldSpec",
    ),
    ("ResolvedDomainSpec", "kinematic", "ResolvedKinematicSpec"),
    ("ResolvedDomainSpec", "custom", "ResolvedCustomSpec"),
    ("ModelSpec", "remote", "RemoteModelSpec"),
    ("ModelSpec", "linear", "LinearModelSpec"),
    ("ModelSpec", "client", "ClientModelSpec"),
    ("ResolvedModelSpec", "remote", "ResolvedRemoteModelSpec"),
    ("ResolvedModelSpec", "linear", "ResolvedLinearModelSpec"),
    ("FeatureMap", "unit_box", "UnitBoxFeatureMap"),
    (
        "FeatureMap",
        "kinematic_prediction",
        "KinematicPredictionFeatureMap",
    ),
    ("FeatureMap", "per_move", "PerMoveFeatureMap"),
    (
        "FeatureMap",
        "action_and_rotation",
        "ActionAndRotationFeatureMap",
    ),
    ("NoisePredictor", "homoscedastic", "HomoscedasticNoise"),
    ("NoisePredictor", "heteroscedastic", "HeteroscedasticNoise"),
];
