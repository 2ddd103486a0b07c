//! The experiment's further models of the same robot (beside the domain's own `f̂`): a coarse
//! simulator, a learned model, a kinematic one — each named, with a cost per call, and each
//! labelling every posted transition with its own deviation, so that one set of executions
//! shows where each model is right.
//!
//! ```json
//! "models": [{"name": "sim", "cost": 20,
//!             "model": {"kind": "remote", "url": "http://robot-pc:9001/predict"}}]
//! ```
//!
//! The domain's own model is named [`DOMAIN_MODEL`] and costs 1: other models' costs are in
//! its calls. An experiment that names no further models stores and shows its settings exactly
//! as before they existed (the list is left out when empty).

use super::{InvalidSetting, ModelSpec};
use crate::domain::custom::wrapping_angles;
use crate::domain::{Domain, NamedModel};
use crate::remote_model::{ModelCalls, ModelUrlPolicy};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Most further models per experiment: each labels every posted transition, so each adds its
/// call to every ingest.
pub const MAX_MODELS: usize = 4;
/// The name of the domain's own model, which no further model may take.
pub const DOMAIN_MODEL: &str = "domain";
/// Longest model name.
pub const MAX_MODEL_NAME_LEN: usize = 32;
/// Largest cost per call, in calls of the domain's own model.
pub const MAX_MODEL_COST: f64 = 1e6;

fn one() -> f64 {
    1.0
}

/// A further model of the experiment's robot, as posted and as stored.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct NamedModelSpec {
    /// The model's name: 1 to 32 letters, digits, `_` or `-`; unique in the experiment and not
    /// `domain` (the domain's own model).
    #[schemars(length(min = 1, max = MAX_MODEL_NAME_LEN))]
    pub name: String,
    /// What one call of the model costs, in calls of the domain's own model (which costs 1):
    /// positive, at most 1e6. Default 1.
    #[serde(default = "one")]
    #[schemars(range(max = MAX_MODEL_COST))]
    pub cost: f64,
    /// Where the model lives. The service calls it for every posted transition.
    pub model: FurtherModelSpec,
}

/// Where a further model lives: one the service calls itself to label every posted transition,
/// or the client's own, whose prediction the client posts with each transition. The tag is
/// `kind`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum FurtherModelSpec {
    /// Served by the robot's own process, as [`ModelSpec::Remote`].
    Remote {
        /// The model's URL (`http://…`), stored as normalised when checked (what is called).
        url: String,
        /// Time limit of one call, in milliseconds. Default 2000; the operator's
        /// `--max-model-timeout-ms` caps it.
        #[serde(default = "super::custom::default_timeout_ms")]
        timeout_ms: u64,
    },
    /// `ŝ' = clip(A s + B a + c)` to the state bounds, as [`ModelSpec::Linear`].
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
    /// The client's own, as [`ModelSpec::Client`]: the client posts its prediction of each
    /// transition (`predictions.<name>` beside `s_next`) and the service labels with it, but
    /// cannot step with it — plans, proposals and maps use the models it can call.
    Client {},
}

impl From<FurtherModelSpec> for ModelSpec {
    fn from(spec: FurtherModelSpec) -> Self {
        match spec {
            FurtherModelSpec::Remote { url, timeout_ms } => ModelSpec::Remote { url, timeout_ms },
            FurtherModelSpec::Linear { a, b, c } => ModelSpec::Linear { a, b, c },
            FurtherModelSpec::Client {} => ModelSpec::Client {},
        }
    }
}

impl FurtherModelSpec {
    /// The kind's name as posted (`remote`, `linear`, `client`).
    pub fn kind(&self) -> &'static str {
        match self {
            Self::Remote { .. } => "remote",
            Self::Linear { .. } => "linear",
            Self::Client {} => "client",
        }
    }

    /// The same model as a [`ModelSpec`] (which resolves and builds it).
    fn spec(&self) -> ModelSpec {
        self.clone().into()
    }

    /// Back from a resolved [`ModelSpec`] of the same kind.
    fn resolved(spec: ModelSpec) -> Self {
        match spec {
            ModelSpec::Remote { url, timeout_ms } => Self::Remote { url, timeout_ms },
            ModelSpec::Linear { a, b, c } => Self::Linear { a, b, c },
            ModelSpec::Client {} => Self::Client {},
        }
    }
}

fn check_name(at: &str, name: &str) -> Result<(), InvalidSetting> {
    let allowed = |c: char| c.is_ascii_alphanumeric() || c == '_' || c == '-';
    if name.is_empty() || name.len() > MAX_MODEL_NAME_LEN || !name.chars().all(allowed) {
        return Err(InvalidSetting::new(
            at,
            format!("must be 1 to {MAX_MODEL_NAME_LEN} ASCII letters, digits, '_' or '-'"),
        ));
    }
    if name == DOMAIN_MODEL {
        return Err(InvalidSetting::new(
            at,
            format!("\"{DOMAIN_MODEL}\" names the domain's own model"),
        ));
    }
    Ok(())
}

/// Checks `models` against the domain they model, fills in their defaults and stores a remote
/// model's URL normalised under `policy`; `periodic` are the state's angle components. Errors
/// name the field (`models[1].cost`).
pub fn resolve(
    mut models: Vec<NamedModelSpec>,
    domain: &dyn Domain,
    periodic: &[usize],
    calls: &Arc<ModelCalls>,
    policy: &ModelUrlPolicy,
) -> Result<Vec<NamedModelSpec>, InvalidSetting> {
    if models.len() > MAX_MODELS {
        return Err(InvalidSetting::new(
            "models",
            format!(
                "at most {MAX_MODELS} models besides the domain's own (each is called for \
                 every posted transition)"
            ),
        ));
    }
    for i in 0..models.len() {
        let at = |field: &str| format!("models[{i}].{field}");
        let m = &mut models[i];
        check_name(&at("name"), &m.name)?;
        if !(m.cost.is_finite() && m.cost > 0.0 && m.cost <= MAX_MODEL_COST) {
            return Err(InvalidSetting::new(
                at("cost"),
                format!("must be a positive number, at most {MAX_MODEL_COST:e}"),
            ));
        }
        let mut spec = m.model.spec();
        spec.resolve(domain.state_space().dim(), policy, &at("model"))?;
        spec.build(
            domain.state_space(),
            domain.action_space(),
            periodic,
            calls,
            &at("model"),
        )?;
        m.model = FurtherModelSpec::resolved(spec);
        let name = &models[i].name;
        if models[..i].iter().any(|earlier| &earlier.name == name) {
            return Err(InvalidSetting::new(
                at("name"),
                format!("\"{name}\" names an earlier model too"),
            ));
        }
    }
    Ok(models)
}

/// Builds resolved `models` (no network: a remote model is first called when used).
pub fn build(
    models: &[NamedModelSpec],
    domain: &dyn Domain,
    periodic: &[usize],
    calls: &Arc<ModelCalls>,
) -> Result<Vec<NamedModel>, InvalidSetting> {
    models
        .iter()
        .enumerate()
        .map(|(i, m)| {
            let model = m.model.spec().build(
                domain.state_space(),
                domain.action_space(),
                periodic,
                calls,
                &format!("models[{i}].model"),
            )?;
            Ok(NamedModel {
                name: m.name.clone(),
                cost: m.cost,
                model: wrapping_angles(model, domain.state_space(), periodic),
            })
        })
        .collect()
}
