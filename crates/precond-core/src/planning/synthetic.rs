//! Cheap deviation models with known answers, for tests, benchmarks and demos — stand-ins for
//! the GP where what matters is the planner, not the learning.

use super::model::DeviationModel;
use crate::domain::IcyGridworld;

/// The same `(μ, σ)` everywhere.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ConstantModel {
    /// Mean deviation.
    pub mu: f64,
    /// Standard deviation (noise included).
    pub sigma: f64,
}

impl DeviationModel for ConstantModel {
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
        vec![(self.mu, self.sigma); features.len() / dim.max(1)]
    }
}

/// What a well-trained MDE knows about an icy gridworld: the x-moves from ice cells deviate
/// (`μ = 2`, the robot ends two cells from where the model said), everything else does not
/// (`μ = 0`); `σ` is the same small value everywhere. Obstacles are not modelled.
#[derive(Debug, Clone)]
pub struct IceModel {
    width: usize,
    height: usize,
    ice: Vec<bool>,
    sigma: f64,
}

impl IceModel {
    /// The model for `grid`'s ice cells, with `σ = sigma` everywhere.
    pub fn new(grid: &IcyGridworld, sigma: f64) -> Self {
        let ice = grid
            .map()
            .iter()
            .flat_map(|row| row.chars().map(|c| c == '~').collect::<Vec<_>>())
            .collect();
        Self {
            width: grid.width(),
            height: grid.height(),
            ice,
            sigma,
        }
    }

    /// Whether the cell `[x, y]` is ice.
    pub fn is_ice(&self, x: usize, y: usize) -> bool {
        x < self.width && y < self.height && self.ice[y * self.width + x]
    }
}

impl DeviationModel for IceModel {
    /// Decodes `φ = (x, y, dx, dy)` scaled to the unit box (see `IcyGridworld::features`).
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
        features
            .chunks(dim.max(1))
            .map(|f| {
                let x = (f[0] * (self.width - 1) as f64).round() as usize;
                let y = (f[1] * (self.height - 1) as f64).round() as usize;
                let dx = 2.0 * f[2] - 1.0;
                let mu = if dx.abs() > 0.5 && self.is_ice(x, y) {
                    2.0
                } else {
                    0.0
                };
                (mu, self.sigma)
            })
            .collect()
    }
}

/// What a learner might know of a 5 × 5 gridworld whose column 2 is a wall with gaps: the
/// rightward moves from the `doubtful` cells `(x, y)` are doubtful (`μ` half of a `d_max` of
/// 0.1, `σ` as large: untrusted at β 2, within with probability 0.84), those from the `through`
/// cells trusted, every other move touching column 2 bumps (`μ = 1`); the rest is trusted.
#[derive(Debug, Clone, PartialEq)]
pub struct WallGapsModel {
    /// Cells whose rightward move is doubtful.
    pub doubtful: Vec<(f64, f64)>,
    /// Cells of column 2 whose rightward move is trusted (the way out of a gap).
    pub through: Vec<(f64, f64)>,
}

impl DeviationModel for WallGapsModel {
    /// Decodes `φ = (x, y, dx, dy)` scaled to the unit box of a 5 × 5 grid.
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
        features
            .chunks(dim.max(1))
            .map(|f| {
                let (x, y) = ((f[0] * 4.0).round(), (f[1] * 4.0).round());
                let dx = 2.0 * f[2] - 1.0;
                if dx == 1.0 && self.doubtful.contains(&(x, y)) {
                    (0.05, 0.05)
                } else if dx == 1.0 && self.through.contains(&(x, y)) {
                    (0.0, 0.001)
                } else if x == 2.0 || x + dx == 2.0 {
                    (1.0, 0.001)
                } else {
                    (0.0, 0.001)
                }
            })
            .collect()
    }
}
