//! The deviation model as the planner sees it: μ and σ of the deviation for feature vectors,
//! and σ as if pending state-actions were labelled (fantasies). The MDE (or any stand-in: the
//! true deviation of a simulator, a synthetic model in tests) plugs in here from outside.

/// A model deviation estimator as the planner sees it: μ and σ (σ includes noise) of the
/// deviation for feature vectors φ(s,a).
pub trait DeviationModel: Sync {
    /// `features` is row-major, `n = features.len() / dim` points of dimension `dim`; returns
    /// (mu, sigma) per point.
    ///
    /// The planner asks for many points at once where it can, and never asks twice for the same
    /// feature vector within one proposal (see [`ModelCache`](super::ModelCache)).
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)>;

    /// (μ, σ) as if the state-actions `pending` (row-major, `dim` each: executions chosen or
    /// posted since the model was fitted) had been labelled as well, at the same
    /// hyperparameters: μ unchanged, σ what they would leave uncertain. The acquisition of
    /// `active` scores candidates with it, so a batch's trajectories do not all chase one
    /// uncertainty; which steps are trusted is still judged by [`predict`](Self::predict).
    /// The default ignores `pending` (a model that cannot fantasise).
    fn predict_fantasised(&self, features: &[f64], pending: &[f64], dim: usize) -> Vec<(f64, f64)> {
        let _ = pending;
        self.predict(features, dim)
    }

    /// [`predict_fantasised`](Self::predict_fantasised) at the same `features` for any number
    /// of alternative pending sets, asked in as many calls of the returned function as suit
    /// the caller: the `spread` acquisition asks it about every candidate of a proposal. A
    /// model may prepare `features` once for all of them and share work between the sets of
    /// one call (the exact GP does both); the default asks anew for each set.
    fn fantasy<'a>(&'a self, features: &'a [f64], dim: usize) -> Fantasy<'a> {
        Box::new(move |pendings| {
            pendings
                .iter()
                .map(|pending| self.predict_fantasised(features, pending, dim))
                .collect()
        })
    }
}

/// What [`DeviationModel::fantasy`] answers: `(μ, σ)` at its features after each of several
/// alternative pending sets (row-major, the features' dimension each), in order.
pub type Fantasy<'a> = Box<dyn Fn(&[&[f64]]) -> Vec<Vec<(f64, f64)>> + 'a>;

/// One of the models a test-time plan may step with ([`Planner::plan_across`]): a dynamics
/// model of the robot, the deviation model of its own precondition (features read *its*
/// prediction), and what one of its calls costs (in any unit, the same for all).
///
/// [`Planner::plan_across`]: super::Planner::plan_across
#[derive(Clone, Copy)]
pub struct PlanModel<'a> {
    /// The dynamics model `f̂_m(s, a)`.
    pub dynamics: &'a dyn crate::domain::DynamicsModel,
    /// The deviation model of `f̂_m`'s precondition.
    pub deviation: &'a dyn DeviationModel,
    /// What one call of `f̂_m` costs.
    pub cost: f64,
}
