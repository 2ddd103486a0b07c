//! Local experts ([`LocalExperts`]): the training transitions split into regions of the feature
//! space, an exact GP fitted on each region's transitions with hyperparameters of its own, and
//! a query answered by the GP of the region whose centre is nearest.
//!
//! One GP over the whole space has one set of length scales: a deviation that is flat across
//! open space and jumps at a shelf, a wall or the edge of a mat gets length scales that blur the
//! jump or that shatter the flat part. Experts each choose their own, so a region with a jump
//! and a region without one are each fitted as they are. The regions are k-means clusters of
//! the training inputs (`⌈n / expert_size⌉` of them, k-means++ seeded, Lloyd iterations), and a
//! region with fewer than [`MIN_EXPERT_POINTS`] transitions is merged into its neighbours.
//!
//! Because a point is answered by exactly one expert, which depends only on the point, the
//! held-out judgements model selection needs are each expert's own closed-form leave-out, and a
//! fantasised batch only moves the expert its pending rows fall to. Far from every training
//! point the nearest expert reverts to its prior, as the single GP does. Fits cost
//! `k · O((n/k)³)` instead of `O(n³)`.

use nalgebra::{DMatrix, DVector};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::gp::{
    Fold, GpError, GpModel, ModelState, NoiseMode, Prediction, Predictor, ValidGpParams,
};

/// A region with fewer training transitions than this is merged into its neighbours.
pub const MIN_EXPERT_POINTS: usize = 20;

/// The default `mde.expert_size`: transitions per expert the regions aim at.
pub const DEFAULT_EXPERT_SIZE: usize = 300;

/// Lloyd iterations of the k-means that places the regions' centres (it stops earlier when
/// no point changes region).
const KMEANS_ITERATIONS: usize = 30;

/// Exact GPs, one per region of the feature space; see the module documentation.
#[derive(Debug, Clone)]
pub struct LocalExperts {
    centres: Vec<Vec<f64>>,
    experts: Vec<GpModel>,
    /// The training rows of each expert, ascending.
    rows: Vec<Vec<usize>>,
    n: usize,
}

/// [`LocalExperts`] as stored: the centres and each expert's GP state. Restoring needs the
/// training data (each expert is an exact GP).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ExpertsState {
    /// The regions' centres, one row of features each.
    pub centres: Vec<Vec<f64>>,
    /// Each region's exact GP, in the order of `centres`.
    pub experts: Vec<ModelState>,
}

/// [`LocalExperts`] as plain numbers (the exported model's `predictor` for this estimator): a
/// point is answered by the expert whose centre is nearest (squared Euclidean distance in
/// feature space, ties to the first).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
pub struct ExpertsPredictor {
    /// The regions' centres, one row of features each.
    pub centres: Vec<Vec<f64>>,
    /// Each region's GP, in the order of `centres`.
    pub experts: Vec<Predictor>,
}

impl ExpertsPredictor {
    /// Input dimension.
    pub fn dim(&self) -> usize {
        self.experts.first().map_or(0, Predictor::dim)
    }

    /// Checks that the parts fit together; the error names the field.
    pub fn check(&self) -> Result<(), String> {
        if self.experts.is_empty() || self.centres.len() != self.experts.len() {
            return Err(format!(
                "experts: one per centre and at least one ({} centres, {} experts)",
                self.centres.len(),
                self.experts.len()
            ));
        }
        let d = self.dim();
        for (i, e) in self.experts.iter().enumerate() {
            e.check().map_err(|e| format!("experts[{i}].{e}"))?;
            if e.dim() != d {
                return Err(format!("experts[{i}]: reads {} features, not {d}", e.dim()));
            }
        }
        if let Some(i) = self
            .centres
            .iter()
            .position(|c| c.len() != d || c.iter().any(|v| !v.is_finite()))
        {
            return Err(format!("centres[{i}]: {d} finite numbers"));
        }
        Ok(())
    }

    /// The expert answering at `x`.
    pub fn expert_at(&self, x: &[f64]) -> &Predictor {
        &self.experts[nearest(&self.centres, x)]
    }
}

/// The index of the centre nearest `x` (squared Euclidean distance, ties to the first).
pub fn nearest(centres: &[Vec<f64>], x: &[f64]) -> usize {
    let mut best = (0, f64::INFINITY);
    for (i, c) in centres.iter().enumerate() {
        let d: f64 = c.iter().zip(x).map(|(a, b)| (a - b) * (a - b)).sum();
        if d < best.1 {
            best = (i, d);
        }
    }
    best.0
}

fn row(x: &DMatrix<f64>, i: usize) -> Vec<f64> {
    x.row(i).iter().copied().collect()
}

/// The rows of `x` nearest each centre, ascending.
fn assign(centres: &[Vec<f64>], x: &DMatrix<f64>) -> Vec<Vec<usize>> {
    let mut groups = vec![Vec::new(); centres.len()];
    for i in 0..x.nrows() {
        groups[nearest(centres, &row(x, i))].push(i);
    }
    groups
}

fn select_rows(x: &DMatrix<f64>, rows: &[usize]) -> DMatrix<f64> {
    x.select_rows(rows.iter())
}

/// `k` centres by k-means++ seeding and Lloyd iterations (deterministic in `seed`).
fn kmeans(x: &DMatrix<f64>, k: usize, seed: u64) -> Vec<Vec<f64>> {
    let n = x.nrows();
    let points: Vec<Vec<f64>> = (0..n).map(|i| row(x, i)).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x6c6f_6361_6c00);
    let mut centres = vec![points[rng.random_range(0..n)].clone()];
    let dist = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(p, q)| (p - q) * (p - q)).sum::<f64>();
    let mut closest: Vec<f64> = points.iter().map(|p| dist(p, &centres[0])).collect();
    while centres.len() < k {
        let total: f64 = closest.iter().sum();
        if total <= 0.0 {
            break; // fewer distinct points than centres
        }
        let mut target = rng.random::<f64>() * total;
        let mut pick = n - 1;
        for (i, d) in closest.iter().enumerate() {
            if target < *d {
                pick = i;
                break;
            }
            target -= d;
        }
        centres.push(points[pick].clone());
        for (c, p) in closest.iter_mut().zip(&points) {
            *c = c.min(dist(p, &points[pick]));
        }
    }
    let mut labels = vec![usize::MAX; n];
    for _ in 0..KMEANS_ITERATIONS {
        let next: Vec<usize> = points.iter().map(|p| nearest(&centres, p)).collect();
        if next == labels {
            break;
        }
        labels = next;
        let d = x.ncols();
        let mut sums = vec![vec![0.0; d]; centres.len()];
        let mut counts = vec![0usize; centres.len()];
        for (p, &l) in points.iter().zip(&labels) {
            counts[l] += 1;
            for (s, v) in sums[l].iter_mut().zip(p) {
                *s += v;
            }
        }
        for ((c, s), &m) in centres.iter_mut().zip(sums).zip(&counts) {
            if m > 0 {
                *c = s.into_iter().map(|v| v / m as f64).collect();
            }
        }
    }
    centres
}

/// The regions' centres for `x`: k-means with `⌈n / size⌉` centres, then the centre of the
/// smallest region removed while that region has fewer than [`MIN_EXPERT_POINTS`] rows (its
/// rows go to their next-nearest centres), so every expert has enough data to fit.
fn regions(x: &DMatrix<f64>, size: usize, seed: u64) -> Vec<Vec<f64>> {
    let n = x.nrows();
    let k = n.div_ceil(size.max(1)).max(1);
    let mut centres = kmeans(x, k, seed);
    loop {
        let groups = assign(&centres, x);
        let smallest = (0..groups.len()).min_by_key(|&i| groups[i].len());
        match smallest {
            Some(i) if centres.len() > 1 && groups[i].len() < MIN_EXPERT_POINTS.min(n) => {
                centres.remove(i);
            }
            _ => return centres,
        }
    }
}

impl LocalExperts {
    /// Fits the experts on `(x, y)`: regions of about `expert_size` rows each
    /// ([`regions`]), an exact GP with `params` on each.
    pub fn fit(
        x: &DMatrix<f64>,
        y: &DVector<f64>,
        params: &ValidGpParams,
        expert_size: usize,
    ) -> Result<Self, GpError> {
        if x.nrows() == 0 || x.nrows() != y.len() {
            return Err(GpError::EmptyData(
                "local experts need at least one row, as many as labels",
            ));
        }
        let centres = regions(x, expert_size, params.params().seed);
        let rows = assign(&centres, x);
        let experts = rows
            .iter()
            .map(|r| GpModel::fit(&select_rows(x, r), &select_y(y, r), params))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self {
            centres,
            experts,
            rows,
            n: x.nrows(),
        })
    }

    /// The experts again from their stored state and the training data, without re-optimising.
    pub fn from_state(
        x: &DMatrix<f64>,
        y: &DVector<f64>,
        state: &ExpertsState,
    ) -> Result<Self, GpError> {
        if state.centres.is_empty() || state.centres.len() != state.experts.len() {
            return Err(GpError::InvalidState(format!(
                "{} centres and {} experts",
                state.centres.len(),
                state.experts.len()
            )));
        }
        if state.centres.iter().any(|c| c.len() != x.ncols()) {
            return Err(GpError::InvalidState(
                "a centre's dimension is not the data's".into(),
            ));
        }
        let rows = assign(&state.centres, x);
        let experts = rows
            .iter()
            .zip(&state.experts)
            .map(|(r, s)| GpModel::from_state(&select_rows(x, r), &select_y(y, r), s))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self {
            centres: state.centres.clone(),
            experts,
            rows,
            n: x.nrows(),
        })
    }

    /// What [`from_state`](Self::from_state) restores.
    pub fn state(&self) -> ExpertsState {
        ExpertsState {
            centres: self.centres.clone(),
            experts: self.experts.iter().map(GpModel::state).collect(),
        }
    }

    /// Training points.
    pub fn n_train(&self) -> usize {
        self.n
    }

    /// The experts, in the order of their centres.
    pub fn experts(&self) -> &[GpModel] {
        &self.experts
    }

    /// The sum of the experts' log marginal likelihoods: the log marginal likelihood of the
    /// model that treats the regions as independent.
    pub fn log_marginal_likelihood(&self) -> f64 {
        self.experts
            .iter()
            .map(GpModel::log_marginal_likelihood)
            .sum()
    }

    /// Homoscedastic when every expert is, else heteroscedastic (an expert with few points
    /// falls back to homoscedastic noise, [`GpModel::fit`]).
    pub fn noise_mode(&self) -> NoiseMode {
        if self
            .experts
            .iter()
            .all(|e| e.noise_mode() == NoiseMode::Homoscedastic)
        {
            NoiseMode::Homoscedastic
        } else {
            NoiseMode::Heteroscedastic
        }
    }

    /// The rows of `x` each expert answers.
    fn split(&self, x: &DMatrix<f64>) -> Vec<Vec<usize>> {
        assign(&self.centres, x)
    }

    /// Each row's prediction by its expert, from `answer(expert, its rows)`.
    fn gather(
        &self,
        x: &DMatrix<f64>,
        answer: impl Fn(usize, &DMatrix<f64>) -> Prediction,
    ) -> Prediction {
        let n = x.nrows();
        let mut out = Prediction {
            mean: vec![0.0; n],
            latent_variance: vec![0.0; n],
            noise_variance: vec![0.0; n],
        };
        for (e, rows) in self.split(x).iter().enumerate() {
            if rows.is_empty() {
                continue;
            }
            let p = answer(e, &select_rows(x, rows));
            for (k, &i) in rows.iter().enumerate() {
                out.mean[i] = p.mean[k];
                out.latent_variance[i] = p.latent_variance[k];
                out.noise_variance[i] = p.noise_variance[k];
            }
        }
        out
    }

    /// Batched predictions, each row by the expert of its region.
    pub fn predict(&self, x: &DMatrix<f64>) -> Prediction {
        self.gather(x, |e, rows| self.experts[e].predict(rows))
    }

    /// Predictions as if `pending` had been observed too: each pending row conditions the
    /// expert of its region only.
    pub fn predict_fantasised(&self, x: &DMatrix<f64>, pending: &DMatrix<f64>) -> Prediction {
        let pending_rows = self.split(pending);
        self.gather(x, |e, rows| {
            if pending_rows[e].is_empty() {
                self.experts[e].predict(rows)
            } else {
                self.experts[e].predict_fantasised(rows, &select_rows(pending, &pending_rows[e]))
            }
        })
    }

    /// Each training row's answer by its expert, from `held_out(expert)` in the expert's order.
    fn scatter(
        &self,
        held_out: impl Fn(usize) -> Option<Vec<(f64, f64)>>,
    ) -> Option<Vec<(f64, f64)>> {
        let mut out = vec![(f64::NAN, f64::NAN); self.n];
        for (e, rows) in self.rows.iter().enumerate() {
            let local = held_out(e)?;
            for (&i, v) in rows.iter().zip(local) {
                out[i] = v;
            }
        }
        Some(out)
    }

    /// Closed-form leave-one-out within each expert ([`GpModel::leave_one_out`]): exact for
    /// this model, since a point's expert does not depend on its label.
    pub fn leave_one_out(&self) -> Option<Vec<(f64, f64)>> {
        self.scatter(|e| self.experts[e].leave_one_out())
    }

    /// [`GpModel::leave_folds_out`] within each expert: a fold's rows in an expert's region
    /// are left out of that expert, and its judged rows there predicted by it.
    pub fn leave_folds_out(&self, folds: &[Fold]) -> Option<Vec<(f64, f64)>> {
        let mut local_of = vec![(0usize, 0usize); self.n];
        for (e, rows) in self.rows.iter().enumerate() {
            for (k, &i) in rows.iter().enumerate() {
                local_of[i] = (e, k);
            }
        }
        let mut per_expert: Vec<Vec<Fold>> = vec![Vec::new(); self.experts.len()];
        for fold in folds {
            let mut judged: Vec<Vec<usize>> = vec![Vec::new(); self.experts.len()];
            let mut rest: Vec<Vec<usize>> = vec![Vec::new(); self.experts.len()];
            for (j, &i) in fold.rows.iter().enumerate() {
                let (e, k) = *local_of.get(i)?;
                if j < fold.judged {
                    judged[e].push(k);
                } else {
                    rest[e].push(k);
                }
            }
            for (e, (mut j, r)) in judged.into_iter().zip(rest).enumerate() {
                if j.is_empty() {
                    continue;
                }
                let count = j.len();
                j.extend(r);
                per_expert[e].push(Fold {
                    rows: j,
                    judged: count,
                });
            }
        }
        self.scatter(|e| self.experts[e].leave_folds_out(&per_expert[e]))
    }

    /// As plain numbers, for the exported model.
    pub fn predictor(&self) -> ExpertsPredictor {
        ExpertsPredictor {
            centres: self.centres.clone(),
            experts: self.experts.iter().map(GpModel::predictor).collect(),
        }
    }

    /// Floats kept in memory: each expert's `n_e²` factor.
    pub fn floats(&self) -> usize {
        self.rows.iter().map(|r| r.len() * r.len()).sum()
    }
}

fn select_y(y: &DVector<f64>, rows: &[usize]) -> DVector<f64> {
    DVector::from_iterator(rows.len(), rows.iter().map(|&i| y[i]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gp::{GpParams, Kernel};

    fn params() -> ValidGpParams {
        GpParams {
            noise: NoiseMode::Homoscedastic,
            kernel: Kernel::Matern52,
            restarts: 0,
            seed: 3,
            ..GpParams::default()
        }
        .check()
        .expect("valid")
    }

    /// `n` points on a line in 2-D (second feature constant) with a deviation that is flat on
    /// the left half and a steep ramp on the right.
    fn step_world(n: usize) -> (DMatrix<f64>, DVector<f64>) {
        let x = DMatrix::from_fn(n, 2, |i, c| {
            if c == 0 {
                i as f64 / (n - 1) as f64
            } else {
                0.5
            }
        });
        let y = DVector::from_fn(n, |i, _| {
            let t = x[(i, 0)];
            if t < 0.5 { 0.01 } else { (t - 0.5) * 4.0 }
        });
        (x, y)
    }

    #[test]
    fn one_region_is_the_exact_gp() {
        let (x, y) = step_world(60);
        let experts = LocalExperts::fit(&x, &y, &params(), 1000).expect("fits");
        let exact = GpModel::fit(&x, &y, &params()).expect("fits");
        assert_eq!(experts.experts().len(), 1);
        let q = DMatrix::from_fn(7, 2, |i, c| if c == 0 { i as f64 / 6.0 } else { 0.4 });
        let (a, b) = (experts.predict(&q), exact.predict(&q));
        for i in 0..7 {
            assert!((a.mean[i] - b.mean[i]).abs() < 1e-12);
            assert!((a.latent_variance[i] - b.latent_variance[i]).abs() < 1e-12);
        }
    }

    #[test]
    fn each_point_is_answered_by_the_expert_of_its_region() {
        let (x, y) = step_world(120);
        let experts = LocalExperts::fit(&x, &y, &params(), 40).expect("fits");
        assert!(experts.experts().len() >= 2, "{}", experts.experts().len());
        let p = experts.predict(&x);
        let groups = assign(&experts.centres, &x);
        for (e, rows) in groups.iter().enumerate() {
            let own = experts.experts()[e].predict(&select_rows(&x, rows));
            for (k, &i) in rows.iter().enumerate() {
                assert_eq!(p.mean[i], own.mean[k]);
            }
        }
    }

    #[test]
    fn regions_too_small_are_merged() {
        let (x, y) = step_world(50);
        // 50 rows at 10 per expert would be 5 regions of about 10 < MIN_EXPERT_POINTS rows.
        let experts = LocalExperts::fit(&x, &y, &params(), 10).expect("fits");
        assert!(
            experts.rows.iter().all(|r| r.len() >= MIN_EXPERT_POINTS),
            "{:?}",
            experts.rows.iter().map(Vec::len).collect::<Vec<_>>()
        );
        assert_eq!(experts.rows.iter().map(Vec::len).sum::<usize>(), 50);
    }

    #[test]
    fn the_state_restores_the_same_predictions() {
        let (x, y) = step_world(100);
        let experts = LocalExperts::fit(&x, &y, &params(), 40).expect("fits");
        let state: ExpertsState =
            serde_json::from_str(&serde_json::to_string(&experts.state()).unwrap()).unwrap();
        let back = LocalExperts::from_state(&x, &y, &state).expect("restores");
        let q = DMatrix::from_fn(11, 2, |i, c| if c == 0 { i as f64 / 10.0 } else { 0.3 });
        let (a, b) = (experts.predict(&q), back.predict(&q));
        for i in 0..11 {
            assert!((a.mean[i] - b.mean[i]).abs() < 1e-9, "{i}");
            assert!(
                (a.latent_variance[i] - b.latent_variance[i]).abs() < 1e-9,
                "{i}"
            );
        }
    }

    #[test]
    fn leaving_folds_out_is_each_experts_leave_out() {
        let (x, y) = step_world(90);
        let experts = LocalExperts::fit(&x, &y, &params(), 30).expect("fits");
        // Singleton folds: the same as leave-one-out.
        let folds: Vec<Fold> = (0..90)
            .map(|i| Fold {
                rows: vec![i],
                judged: 1,
            })
            .collect();
        let a = experts.leave_folds_out(&folds).expect("closed form");
        let b = experts.leave_one_out().expect("closed form");
        for i in 0..90 {
            assert!((a[i].0 - b[i].0).abs() < 1e-9 && (a[i].1 - b[i].1).abs() < 1e-9);
        }
        // And a point's leave-one-out is its expert's, found by refitting that expert without
        // it at the same hyperparameters.
        let e = 0;
        let rows = &experts.rows[e];
        let i = rows[rows.len() / 2];
        let rest: Vec<usize> = rows.iter().copied().filter(|&r| r != i).collect();
        let state = ModelState {
            n_train: rest.len(),
            ..experts.experts()[e].state()
        };
        let without =
            GpModel::from_state(&select_rows(&x, &rest), &select_y(&y, &rest), &state).unwrap();
        let p = without.predict(&select_rows(&x, &[i]));
        assert!(
            (y[i] - p.mean[0] - b[i].0).abs() < 1e-6,
            "{} {}",
            p.mean[0],
            b[i].0
        );
    }

    #[test]
    fn a_fantasised_row_moves_only_its_experts_answers() {
        let (x, y) = step_world(120);
        let experts = LocalExperts::fit(&x, &y, &params(), 40).expect("fits");
        let q = DMatrix::from_fn(13, 2, |i, c| if c == 0 { i as f64 / 12.0 } else { 0.9 });
        let pending = DMatrix::from_row_slice(1, 2, &[0.0, 0.9]);
        let before = experts.predict(&q);
        let after = experts.predict_fantasised(&q, &pending);
        let home = nearest(&experts.centres, &[0.0, 0.9]);
        for i in 0..13 {
            let e = nearest(&experts.centres, &row(&q, i));
            if e == home {
                assert!(after.latent_variance[i] <= before.latent_variance[i] + 1e-12);
            } else {
                assert_eq!(after.latent_variance[i], before.latent_variance[i]);
            }
        }
        assert!(after.latent_variance[0] < before.latent_variance[0]);
    }

    #[test]
    fn a_flat_region_keeps_its_long_length_scales_beside_a_wiggly_one() {
        // Flat on the left, a fast sine on the right: one GP takes the short length scale
        // everywhere and is unsure between the flat region's points; the experts are not,
        // and predict the function between the training points as well.
        let n = 160;
        let f = |t: f64| {
            if t < 0.5 {
                0.02
            } else {
                0.02 + 0.2 * (40.0 * (t - 0.5)).sin()
            }
        };
        let x = DMatrix::from_fn(n, 2, |i, c| {
            if c == 0 {
                i as f64 / (n - 1) as f64
            } else {
                0.5
            }
        });
        let y = DVector::from_fn(n, |i, _| f(x[(i, 0)]));
        let single = GpModel::fit(&x, &y, &params()).expect("fits");
        let experts = LocalExperts::fit(&x, &y, &params(), 60).expect("fits");
        assert!(experts.experts().len() >= 2);
        // Midpoints between training points.
        let q = DMatrix::from_fn(n - 1, 2, |i, c| {
            if c == 0 {
                (i as f64 + 0.5) / (n - 1) as f64
            } else {
                0.5
            }
        });
        let (ps, pe) = (single.predict(&q), experts.predict(&q));
        let flat: Vec<usize> = (0..n - 1).filter(|&i| q[(i, 0)] < 0.4).collect();
        let mean =
            |v: &[f64], rows: &[usize]| rows.iter().map(|&i| v[i]).sum::<f64>() / rows.len() as f64;
        let (sd_s, sd_e) = (mean(&ps.std(), &flat), mean(&pe.std(), &flat));
        assert!(
            sd_e < 0.1 * sd_s,
            "flat region σ: experts {sd_e}, single {sd_s}"
        );
        let err = |p: &Prediction| {
            (0..n - 1)
                .map(|i| (p.mean[i] - f(q[(i, 0)])).abs())
                .sum::<f64>()
                / (n - 1) as f64
        };
        assert!(
            err(&pe) < err(&ps),
            "error: experts {}, single {}",
            err(&pe),
            err(&ps)
        );
    }
}
