//! The continuous worlds: robots whose own model is kinematic — "the state moves by the action",
//! `f̂(s, a) = clip(s + a)` ([`Kinematic`]) — while the true dynamics are physics the model
//! ignores. Each world is a kinematic domain (what the robot tells precond), a tolerance, and a
//! simulator.
//!
//! - [`ContinuousWorld::Arm`]: a three-joint arm in a vertical plane ([`ArmSim`]): joint-space
//!   state and actions; gravity sag (smooth), actuators too weak to hold the arm stretched out,
//!   contact with a shelf and the floor (sharp).
//! - [`ContinuousWorld::Base`]: a mobile base ([`BaseSim`]): a slippery slope where only short
//!   moves keep within tolerance, a crosswind corridor, a hidden box.
//! - [`ContinuousWorld::Pusher`]: a pushed puck ([`PusherSim`]): it slides on after each push,
//!   far on a wet patch whose friction falls smoothly, and bounces off a post and the walls.

use super::World;
use super::arm::{ArmParams, ArmSim};
use super::base::{BaseParams, BaseSim};
use super::pusher::{PusherParams, PusherSim};
use crate::domain::{Domain, Kinematic, KinematicFeatures, KinematicParams, LocalModel, Problem};
use rand::RngCore;
use std::sync::Arc;

/// A continuous world of the harness (see the module docs).
#[derive(Debug, Clone)]
pub enum ContinuousWorld {
    /// The arm.
    Arm(Arc<ArmSim>),
    /// The mobile base.
    Base(Arc<BaseSim>),
    /// The pushed puck.
    Pusher(Arc<PusherSim>),
}

impl ContinuousWorld {
    /// The arm in its default build.
    pub fn arm() -> Self {
        Self::Arm(Arc::new(ArmSim::new(ArmParams::default())))
    }

    /// The base on its default ground.
    pub fn base() -> Self {
        Self::Base(Arc::new(BaseSim::new(BaseParams::default())))
    }

    /// The puck on its default floor.
    pub fn pusher() -> Self {
        Self::Pusher(Arc::new(PusherSim::new(PusherParams::default())))
    }

    /// The world's name: `arm`, `base` or `pusher`.
    pub fn name(&self) -> &'static str {
        match self {
            Self::Arm(_) => "arm",
            Self::Base(_) => "base",
            Self::Pusher(_) => "pusher",
        }
    }

    /// The robot's own model of the world, as a kinematic domain's parameters: the state
    /// bounds (joint limits, the arena), the action bounds and the goal radius; no obstacles
    /// (the robot does not know them).
    pub fn params(&self) -> KinematicParams {
        match self {
            Self::Arm(arm) => {
                let p = arm.params();
                KinematicParams {
                    state_low: p.joint_low.clone(),
                    state_high: p.joint_high.clone(),
                    action_low: vec![-0.25; p.lengths.len()],
                    action_high: vec![0.25; p.lengths.len()],
                    obstacles: Vec::new(),
                    goal_radius: 0.15,
                    features: KinematicFeatures::default(),
                }
            }
            // The base's arena is the default kinematic domain: the unit square, moves of at
            // most 0.1 per axis, goal radius 0.05.
            Self::Base(_) => KinematicParams::default(),
            Self::Pusher(sim) => {
                let side = sim.params().side;
                KinematicParams {
                    state_low: vec![0.0, 0.0],
                    state_high: vec![side, side],
                    action_low: vec![-0.12, -0.12],
                    action_high: vec![0.12, 0.12],
                    obstacles: Vec::new(),
                    goal_radius: 0.05,
                    features: KinematicFeatures::default(),
                }
            }
        }
    }

    /// The robot's model as a domain.
    pub fn domain(&self) -> Kinematic {
        Kinematic::new(self.params()).expect("the built-in worlds' parameters are valid")
    }

    /// The tolerance `d_max` of the world's experiments (rad for the arm, m otherwise).
    pub fn d_max(&self) -> f64 {
        match self {
            Self::Arm(_) => 0.04,
            Self::Base(_) | Self::Pusher(_) => 0.02,
        }
    }

    /// The true next state.
    pub fn step(&self, s: &[f64], a: &[f64]) -> Vec<f64> {
        match self {
            Self::Arm(arm) => arm.step(s, a),
            Self::Base(base) => base.step(s, a),
            Self::Pusher(sim) => sim.step(s, a),
        }
    }

    /// Whether a robot can be in state `s` (not inside an obstacle).
    pub fn possible(&self, s: &[f64]) -> bool {
        match self {
            Self::Arm(arm) => !arm.in_contact(s),
            Self::Base(base) => !base.blocked([s[0], s[1]]),
            Self::Pusher(sim) => !sim.in_post([s[0], s[1]]),
        }
    }

    /// A problem from the domain's distribution whose start and goal are possible states
    /// (redrawn up to 100 times).
    pub fn sample_problem(&self, domain: &Kinematic, rng: &mut dyn RngCore) -> Problem {
        let mut p = domain.sample_problem(rng);
        for _ in 0..100 {
            if self.possible(p.start()) && self.possible(p.goal()) {
                break;
            }
            p = domain.sample_problem(rng);
        }
        p
    }

    /// The true deviation `d(f̂(s, a), f(s, a))` of one state-action.
    pub fn true_deviation(&self, domain: &Kinematic, s: &[f64], a: &[f64]) -> f64 {
        domain.distance(&domain.predict(s, a), &self.step(s, a))
    }

    /// A simulator of this world.
    pub fn world(&self) -> Box<dyn World> {
        Box::new(ContinuousSim(self.clone()))
    }
}

/// [`ContinuousWorld`] as a [`World`] (deterministic: `reset` draws nothing).
#[derive(Debug)]
struct ContinuousSim(ContinuousWorld);

impl World for ContinuousSim {
    fn reset(&mut self, _rng: &mut dyn RngCore) {}

    fn step(&mut self, s: &[f64], a: &[f64]) -> Vec<f64> {
        self.0.step(s, a)
    }
}
