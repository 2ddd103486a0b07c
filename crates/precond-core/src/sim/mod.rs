//! The true dynamics of the built-in worlds (simulators).
//!
//! The planner never sees these: they play the robot in experiments and tests. A [`World`] is
//! built from the domain it simulates ([`Simulated::world`]), so that both share one geometry or
//! layout.
//!
//! - [`gridworld`]: the icy gridworld (ice reverses x-moves, obstacles and edges block).
//! - [`water_plant`]: the 2D plant-watering scene (swept collisions, water as falling particles
//!   deflected by leaves that move a little between episodes).
//! - [`continuous`]: the continuous worlds whose robots model themselves kinematically —
//!   [`arm`] (a three-joint arm under gravity with weak actuators and contact), [`base`] (a
//!   mobile base with slip, wind and a hidden box), [`pusher`] (a puck that slides on after
//!   each push).

pub mod arm;
pub mod base;
pub mod continuous;
pub mod gridworld;
pub mod pusher;
pub mod water_plant;

pub use continuous::ContinuousWorld;

pub use gridworld::IcyGridworldSim;
pub use water_plant::{PourOutcome, WaterPlantSim, WaterPlantSimParams};

use rand::RngCore;

/// True dynamics of a world: the "robot" that executes actions.
///
/// `step` takes the state the robot is in and the action it executes and returns the state it
/// ends in. It never panics on a state or action of the matching domain; actions that the domain
/// would reject (wrong form) are still executed in some documented way.
pub trait World: Send + std::fmt::Debug {
    /// Starts a new episode. Worlds with per-episode variation (the water plant's leaves) draw it
    /// here from `rng`; the same seed gives the same episode.
    fn reset(&mut self, rng: &mut dyn RngCore);

    /// Executes action `a` from state `s` and returns the next state.
    fn step(&mut self, s: &[f64], a: &[f64]) -> Vec<f64>;
}

/// A domain that has a built-in simulator.
pub trait Simulated {
    /// The true dynamics matching this domain (same layout or geometry), in its nominal episode;
    /// call [`World::reset`] to draw a new one.
    fn world(&self) -> Box<dyn World>;
}

impl Simulated for crate::domain::IcyGridworld {
    fn world(&self) -> Box<dyn World> {
        Box::new(IcyGridworldSim::new(self))
    }
}

impl Simulated for crate::domain::WaterPlant {
    fn world(&self) -> Box<dyn World> {
        Box::new(WaterPlantSim::new(self))
    }
}
