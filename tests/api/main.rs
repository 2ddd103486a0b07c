//! Integration tests over a real socket and a real SQLite file.

mod contract;
mod experiments;
mod helpers;
mod learning;
mod trajectories;
