//! Gridworld layouts for the harness: the default map, a map read from a file, or seeded random
//! maps (sizes 10–20 with a wall with gaps, ice bands and obstacle blocks), so the method is
//! measured on many worlds and not on one.

use anyhow::Context;
use precond_core::domain::DEFAULT_MAP;
use precond_core::domain::IcyGridworld;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::path::Path;

/// A named gridworld map.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Layout {
    /// Its name: `default`, the file's stem, or `random-<k>`.
    pub name: String,
    /// Rows of `.`, `#` and `~` (see [`DEFAULT_MAP`]).
    pub map: Vec<String>,
}

impl Layout {
    /// The documented 12×12 map.
    pub fn default_map() -> Self {
        Self {
            name: "default".into(),
            map: DEFAULT_MAP.iter().map(|r| r.to_string()).collect(),
        }
    }

    /// A map read from a text file: one row per line (row `y = 0` first), blank lines and lines
    /// starting with `;` ignored.
    pub fn from_file(path: &Path) -> anyhow::Result<Self> {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let map: Vec<String> = text
            .lines()
            .map(str::trim_end)
            .filter(|l| !l.is_empty() && !l.starts_with(';'))
            .map(String::from)
            .collect();
        IcyGridworld::new(&map).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        let name = path
            .file_stem()
            .and_then(|s| s.to_str())
            .unwrap_or("map")
            .to_string();
        Ok(Self { name, map })
    }

    /// The `k`-th seeded random map: a side of 10–20 cells each way, a wall across the middle
    /// third (horizontal or vertical) with one or two gaps of 1–3 cells, one or two ice bands of
    /// 1–2 rows spanning at least half the width, and up to three obstacle blocks. Cells cut
    /// off from the largest open region become obstacles, so every open cell is reachable.
    pub fn random(k: u64) -> Self {
        let mut rng =
            ChaCha8Rng::seed_from_u64(precond_core::seed::mix(0x6c61_796f_7574, k as i64));
        let w = rng.random_range(10..=20usize);
        let h = rng.random_range(10..=20usize);
        let mut g = vec![vec!['.'; w]; h];
        // The wall.
        let horizontal = rng.random_bool(0.5);
        let (len, across) = if horizontal { (w, h) } else { (h, w) };
        let at = rng.random_range(across / 3..=(2 * across) / 3);
        let mut wall = vec![true; len];
        for _ in 0..rng.random_range(1..=2) {
            let width = rng.random_range(1..=3usize);
            let from = rng.random_range(0..=len - width);
            wall[from..from + width].iter_mut().for_each(|c| *c = false);
        }
        // Ice bands, on rows away from a horizontal wall.
        for _ in 0..rng.random_range(1..=2) {
            let rows = rng.random_range(1..=2usize);
            let y0 = rng.random_range(0..=h - rows);
            let span = rng.random_range(w / 2..=w);
            let x0 = rng.random_range(0..=w - span);
            for row in g.iter_mut().skip(y0).take(rows) {
                row[x0..x0 + span].iter_mut().for_each(|c| *c = '~');
            }
        }
        for (i, &blocked) in wall.iter().enumerate() {
            if blocked {
                let (x, y) = if horizontal { (i, at) } else { (at, i) };
                g[y][x] = '#';
            }
        }
        // Obstacle blocks of 1×1 to 2×2.
        for _ in 0..rng.random_range(0..=3) {
            let (bw, bh) = (rng.random_range(1..=2usize), rng.random_range(1..=2usize));
            let (x0, y0) = (rng.random_range(0..=w - bw), rng.random_range(0..=h - bh));
            for row in g.iter_mut().skip(y0).take(bh) {
                row[x0..x0 + bw].iter_mut().for_each(|c| *c = '#');
            }
        }
        keep_largest_region(&mut g);
        Self {
            name: format!("random-{k}"),
            map: g.into_iter().map(|r| r.into_iter().collect()).collect(),
        }
    }
}

/// Turns every open cell outside the largest 4-connected open region into an obstacle.
fn keep_largest_region(g: &mut [Vec<char>]) {
    let (h, w) = (g.len(), g[0].len());
    let mut region = vec![usize::MAX; w * h];
    let mut sizes = Vec::new();
    for start in 0..w * h {
        if region[start] != usize::MAX || g[start / w][start % w] == '#' {
            continue;
        }
        let id = sizes.len();
        let mut stack = vec![start];
        region[start] = id;
        let mut size = 0;
        while let Some(c) = stack.pop() {
            size += 1;
            let (x, y) = (c % w, c / w);
            let mut push = |nx: usize, ny: usize| {
                let n = ny * w + nx;
                if region[n] == usize::MAX && g[ny][nx] != '#' {
                    region[n] = id;
                    stack.push(n);
                }
            };
            if x > 0 {
                push(x - 1, y);
            }
            if x + 1 < w {
                push(x + 1, y);
            }
            if y > 0 {
                push(x, y - 1);
            }
            if y + 1 < h {
                push(x, y + 1);
            }
        }
        sizes.push(size);
    }
    let Some(largest) = (0..sizes.len()).max_by_key(|&i| sizes[i]) else {
        return;
    };
    for (c, &r) in region.iter().enumerate() {
        if r != usize::MAX && r != largest {
            g[c / w][c % w] = '#';
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn random_maps_are_seeded_valid_and_connected() {
        for k in 0..50 {
            let l = Layout::random(k);
            assert_eq!(l, Layout::random(k), "map {k} is not reproducible");
            let g = IcyGridworld::new(&l.map).expect("a valid map");
            assert!((10..=20).contains(&g.width()) && (10..=20).contains(&g.height()));
            assert!(l.map.iter().any(|r| r.contains('~')), "map {k} has no ice");
            assert!(l.map.iter().any(|r| r.contains('#')), "map {k} has no wall");
            // Every open cell is reachable from the first one.
            let mut grid: Vec<Vec<char>> = l.map.iter().map(|r| r.chars().collect()).collect();
            let open_before = grid.iter().flatten().filter(|c| **c != '#').count();
            keep_largest_region(&mut grid);
            let open_after = grid.iter().flatten().filter(|c| **c != '#').count();
            assert_eq!(open_before, open_after, "map {k} has a cut-off region");
        }
        assert_ne!(Layout::random(0).map, Layout::random(1).map);
    }

    #[test]
    fn keeps_only_the_largest_region() {
        let mut g: Vec<Vec<char>> = ["..#.", "..#.", "###."]
            .iter()
            .map(|r| r.chars().collect())
            .collect();
        keep_largest_region(&mut g);
        let rows: Vec<String> = g.into_iter().map(|r| r.into_iter().collect()).collect();
        assert_eq!(rows, ["..##", "..##", "####"]);
    }
}
