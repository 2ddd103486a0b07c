//! Integration tests over a real socket and a real SQLite file.

mod auth;
mod contract;
mod custom;
mod dashboard;
mod executions;
mod experiments;
mod generalisation;
mod helpers;
mod import;
mod learning;
mod limits;
mod model_server;
mod trajectories;
mod upgrade;
