//! Integration tests over a real socket and a real SQLite file.

mod auth;
#[path = "../common/mod.rs"]
mod common;
mod continuous;
mod contract;
mod custom;
mod dashboard;
mod estimators;
mod exclusions;
mod executions;
mod experiments;
mod export;
mod generalisation;
mod helpers;
mod import;
mod learning;
mod limits;
mod model_server;
mod models;
mod posture;
mod remote;
mod trajectories;
mod upgrade;
