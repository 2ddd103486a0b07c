//! The icy gridworld's true dynamics (DESIGN.md §2).
//!
//! From an ice cell the two x-moves are reversed: the robot ends one cell *behind* where it
//! started (`s − a`), two cells from where it meant to go. The y-moves are never affected. A move
//! that would leave the grid or enter an obstacle leaves the robot where it is; this also holds
//! for the reversed move on ice.

use super::World;
use crate::domain::{Cell, IcyGridworld};
use rand::RngCore;

/// The icy gridworld simulator over a layout (see [`IcyGridworld`]).
#[derive(Debug, Clone)]
pub struct IcyGridworldSim {
    /// The layout; only its cells are used.
    grid: IcyGridworld,
}

impl IcyGridworldSim {
    /// A simulator over the domain's layout.
    pub fn new(domain: &IcyGridworld) -> Self {
        Self {
            grid: domain.clone(),
        }
    }

    /// The cell the robot ends in after move `(dx, dy)` from cell `(x, y)`.
    pub fn next_cell(&self, (x, y): (i64, i64), (dx, dy): (i64, i64)) -> (i64, i64) {
        let (dx, dy) = match self.grid.cell(x, y) {
            Some(Cell::Ice) => (-dx, dy),
            _ => (dx, dy),
        };
        let (nx, ny) = (x + dx, y + dy);
        match self.grid.cell(nx, ny) {
            Some(Cell::Free) | Some(Cell::Ice) => (nx, ny),
            Some(Cell::Obstacle) | None => (x, y),
        }
    }
}

impl World for IcyGridworldSim {
    /// The gridworld has no per-episode variation.
    fn reset(&mut self, _rng: &mut dyn RngCore) {}

    /// `s = [x, y]` and `a` one of the four unit moves; components are rounded to the nearest
    /// integer (a state or move that is not one stays as close to the rules as it can).
    fn step(&mut self, s: &[f64], a: &[f64]) -> Vec<f64> {
        let cell = (s[0].round() as i64, s[1].round() as i64);
        let mv = (a[0].round() as i64, a[1].round() as i64);
        let (x, y) = self.next_cell(cell, mv);
        vec![x as f64, y as f64]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::{DEFAULT_MAP, Domain, LocalModel};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    const MOVES: [[f64; 2]; 4] = [[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]];

    fn world() -> IcyGridworldSim {
        IcyGridworldSim::new(&IcyGridworld::default_layout())
    }

    #[test]
    fn the_default_map_has_the_documented_ice_and_wall() {
        let g = IcyGridworld::default_layout();
        assert_eq!(DEFAULT_MAP.len(), 12);
        assert_eq!(g.cell(2, 2), Some(Cell::Ice));
        assert_eq!(g.cell(0, 6), Some(Cell::Obstacle));
        assert_eq!(g.cell(5, 6), Some(Cell::Free));
    }

    #[test]
    fn on_ice_the_x_moves_are_reversed() {
        let mut w = world();
        // (4, 2) is ice: moving right ends one cell left of the start, and vice versa.
        assert_eq!(w.step(&[4.0, 2.0], &[1.0, 0.0]), vec![3.0, 2.0]);
        assert_eq!(w.step(&[4.0, 2.0], &[-1.0, 0.0]), vec![5.0, 2.0]);
        // Two cells from where the model says the robot goes.
        let g = IcyGridworld::default_layout();
        let pred = g.predict(&[4.0, 2.0], &[1.0, 0.0]);
        assert_eq!(pred, vec![5.0, 2.0]);
        assert!((g.deviation(&[4.0, 2.0], &[1.0, 0.0], &[3.0, 2.0]) - 2.0).abs() < 1e-12);
    }

    #[test]
    fn on_ice_the_y_moves_are_normal() {
        let mut w = world();
        assert_eq!(w.step(&[4.0, 2.0], &[0.0, 1.0]), vec![4.0, 3.0]);
        assert_eq!(w.step(&[4.0, 3.0], &[0.0, -1.0]), vec![4.0, 2.0]);
        assert_eq!(w.step(&[4.0, 3.0], &[0.0, 1.0]), vec![4.0, 4.0]);
    }

    #[test]
    fn off_ice_moves_go_where_intended() {
        let mut w = world();
        for m in MOVES {
            let s = [5.0, 4.0];
            let next = w.step(&s, &m);
            assert_eq!(next, vec![s[0] + m[0], s[1] + m[1]]);
        }
        // Stepping onto ice is an ordinary move; only moves *from* ice are reversed.
        assert_eq!(w.step(&[1.0, 2.0], &[1.0, 0.0]), vec![2.0, 2.0]);
    }

    #[test]
    fn obstacles_block_moves() {
        let mut w = world();
        // Row 6 is a wall with a gap at x = 5..6.
        assert_eq!(w.step(&[2.0, 5.0], &[0.0, 1.0]), vec![2.0, 5.0]);
        assert_eq!(w.step(&[2.0, 7.0], &[0.0, -1.0]), vec![2.0, 7.0]);
        assert_eq!(w.step(&[5.0, 5.0], &[0.0, 1.0]), vec![5.0, 6.0]);
        // Inside the gap, the wall blocks sideways moves.
        assert_eq!(w.step(&[5.0, 6.0], &[-1.0, 0.0]), vec![5.0, 6.0]);
        assert_eq!(w.step(&[6.0, 6.0], &[1.0, 0.0]), vec![6.0, 6.0]);
    }

    #[test]
    fn the_edges_block_moves() {
        let mut w = world();
        assert_eq!(w.step(&[0.0, 0.0], &[-1.0, 0.0]), vec![0.0, 0.0]);
        assert_eq!(w.step(&[0.0, 0.0], &[0.0, -1.0]), vec![0.0, 0.0]);
        assert_eq!(w.step(&[11.0, 11.0], &[1.0, 0.0]), vec![11.0, 11.0]);
        assert_eq!(w.step(&[11.0, 11.0], &[0.0, 1.0]), vec![11.0, 11.0]);
    }

    #[test]
    fn a_reversed_move_is_blocked_by_edges_and_obstacles() {
        // Ice at the left edge: moving right would slip off the grid, so the robot stays.
        let g = IcyGridworld::new(&["~..", "#~.", "..."]).unwrap();
        let mut w = IcyGridworldSim::new(&g);
        assert_eq!(w.step(&[0.0, 0.0], &[1.0, 0.0]), vec![0.0, 0.0]);
        // Ice at (1, 1) with an obstacle at (0, 1): the reversed right-move is blocked.
        assert_eq!(w.step(&[1.0, 1.0], &[1.0, 0.0]), vec![1.0, 1.0]);
        // The reversed left-move from (1, 1) goes to (2, 1).
        assert_eq!(w.step(&[1.0, 1.0], &[-1.0, 0.0]), vec![2.0, 1.0]);
    }

    #[test]
    fn the_model_is_exact_off_ice_away_from_obstacles() {
        let g = IcyGridworld::default_layout();
        let mut w = g.world_for_test();
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        w.reset(&mut rng);
        let mut agree = 0;
        let mut total = 0;
        for s in g.open_cells() {
            for m in MOVES {
                let real = w.step(&s, &m);
                let dev = g.deviation(&s, &m, &real);
                let on_ice = g.cell(s[0] as i64, s[1] as i64) == Some(Cell::Ice);
                let into = g.cell((s[0] + m[0]) as i64, (s[1] + m[1]) as i64);
                if !on_ice && into != Some(Cell::Obstacle) {
                    assert!(dev < g.default_d_max(), "{s:?} {m:?}");
                    agree += 1;
                }
                total += 1;
            }
        }
        assert!(agree > total / 2);
    }

    trait WorldForTest {
        fn world_for_test(&self) -> Box<dyn World>;
    }
    impl WorldForTest for IcyGridworld {
        fn world_for_test(&self) -> Box<dyn World> {
            use crate::sim::Simulated;
            self.world()
        }
    }
}
