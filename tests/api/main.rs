//! Integration tests over a real socket and a real SQLite file.

mod contract;
mod custom;
mod dashboard;
mod experiments;
mod helpers;
mod learning;
mod model_server;
mod trajectories;
