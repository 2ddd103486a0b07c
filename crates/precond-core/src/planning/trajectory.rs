//! A planned trajectory, the value every part of the planner passes on: grown by an RRT run,
//! scored by the acquisition, judged when the client posts it, chosen by a strategy.

/// A planned trajectory: predicted states and the actions between them, with the deviation
/// model's answer at each step.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    /// Predicted states `s_0 = start, s_{t+1} = f̂(s_t, a_t)`; one more than `actions`.
    pub states: Vec<Vec<f64>>,
    /// Actions `a_t`.
    pub actions: Vec<Vec<f64>>,
    /// `μ(φ(s_t, a_t))`, per action.
    pub mu: Vec<f64>,
    /// `σ(φ(s_t, a_t))` (noise included), per action.
    pub sigma: Vec<f64>,
}

impl Trajectory {
    /// Number of actions.
    pub fn len(&self) -> usize {
        self.actions.len()
    }

    /// Whether it has no action (the start already satisfies the goal).
    pub fn is_empty(&self) -> bool {
        self.actions.is_empty()
    }

    /// Each step `(s_t, a_t, s_{t+1})`: a state, its action and the predicted state after it
    /// (`f̂(s_t, a_t)`, what [`Domain::features`](crate::domain::Domain::features) reads).
    pub fn steps(&self) -> impl Iterator<Item = (&[f64], &[f64], &[f64])> {
        self.states
            .iter()
            .zip(&self.actions)
            .zip(self.states.iter().skip(1))
            .map(|((s, a), next)| (s.as_slice(), a.as_slice(), next.as_slice()))
    }
}
