//! The MDE feature map `φ(s, a)` as data ([`FeatureMap`]): what a program outside this server
//! needs to compute a domain's features itself — the exported model (`mde::export`) carries it
//! so that a robot's controller can judge its own state-actions.
//!
//! Every built-in domain's [`Domain::features`](super::Domain::features) equals its
//! [`Domain::feature_map`](super::Domain::feature_map)'s [`FeatureMap::features`] to the bit
//! (tested per domain below), so the data describes exactly what the server computes.

use serde::{Deserialize, Serialize};

/// A domain's feature map, tagged `kind`.
///
/// "Scaled to the unit box" means `(v − low) / (high − low)`, or `0` for a component whose
/// bounds coincide (`high = low`); it is not clamped unless said.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum FeatureMap {
    /// The listed state components, then the listed action components, each scaled to the unit
    /// box by its own bounds: the kinematic domain (every component), the icy gridworld's
    /// `scaled` features (every component: `(x, y, dx, dy)`) and a custom domain
    /// (`features.state`, `features.action`).
    UnitBox {
        /// Lower bounds of every state component.
        state_low: Vec<f64>,
        /// Upper bounds of every state component.
        state_high: Vec<f64>,
        /// Lower bounds of every action component.
        action_low: Vec<f64>,
        /// Upper bounds of every action component.
        action_high: Vec<f64>,
        /// The state components that feed the features, in order (0-based indices).
        state_components: Vec<usize>,
        /// The action components that feed the features after them, in order.
        action_components: Vec<usize>,
        /// Whether the length of the listed action components follows.
        #[serde(default, skip_serializing_if = "std::ops::Not::not")]
        action_length: bool,
        /// Components of the model's prediction `ŝ' = f̂(s, a)` that follow, each scaled to the
        /// unit box by its state bounds (a custom domain's `features.prediction`): where a move
        /// ends, which decides most of what a model ignores (a contact, a slope, a slippery
        /// patch). The caller supplies `ŝ'` (the model lives elsewhere).
        #[serde(default, skip_serializing_if = "Vec::is_empty")]
        prediction_components: Vec<usize>,
        /// Weights of the domain's distance, for `move_length` (empty without it).
        #[serde(default, skip_serializing_if = "Vec::is_empty")]
        weights: Vec<f64>,
        /// Whether the length of the predicted move follows as the last feature:
        /// `d(ŝ', s) / d(high, low)` in the domain's distance (weights `weights`), in `[0, 1]`
        /// for predictions within the bounds ([`weighted_move_fraction`]).
        #[serde(default, skip_serializing_if = "std::ops::Not::not")]
        move_length: bool,
        /// State components that are angles (a heading, a continuous joint), their period
        /// `high − low`: each listed in `state_components` or `prediction_components` feeds two
        /// features instead of one, `(1 + cos 2πu) / 2` and `(1 + sin 2πu) / 2` with `u` its
        /// unit-box value (so that both sides of the wrap are near), and the move's length
        /// takes the shorter way round ([`periodic_difference`]).
        #[serde(default, skip_serializing_if = "Vec::is_empty")]
        periodic: Vec<usize>,
    },
    /// The kinematic domain's `state_action_prediction` features: the state, then the action,
    /// then the model's prediction `clip(s + a)` (each component clamped to the state bounds),
    /// each scaled to the unit box by its own bounds — `3n` features for `n` components; with
    /// `move_length` (`state_action_prediction_length`) one more, the length of the predicted
    /// move ([`predicted_move_fraction`]) — `3n + 1`.
    KinematicPrediction {
        /// Lower bounds of every state component.
        state_low: Vec<f64>,
        /// Upper bounds of every state component.
        state_high: Vec<f64>,
        /// Lower bounds of every action component.
        action_low: Vec<f64>,
        /// Upper bounds of every action component.
        action_high: Vec<f64>,
        /// Whether the length of the predicted move follows as the last feature.
        #[serde(default, skip_serializing_if = "std::ops::Not::not")]
        move_length: bool,
    },
    /// The icy gridworld's `per_move` features: with `K` moves and `k` the index of the move
    /// equal to `a` (every component within `tolerance`), `3K` features, zero but for the
    /// state scaled to the unit box at positions `2k, 2k + 1` and a one at position `2K + k`.
    PerMove {
        /// Lower bounds of the state components.
        state_low: Vec<f64>,
        /// Upper bounds of the state components.
        state_high: Vec<f64>,
        /// The moves, in order.
        moves: Vec<Vec<f64>>,
        /// How far an action may lie from its move in each component.
        tolerance: f64,
    },
    /// The water plant's features: every action component scaled to the unit box and clamped
    /// to `[0, 1]`, then `1` if the action rotates (`|a[action_angle] − s[state_angle]| >
    /// tolerance`), else `0`.
    ActionAndRotation {
        /// Lower bounds of the action components.
        action_low: Vec<f64>,
        /// Upper bounds of the action components.
        action_high: Vec<f64>,
        /// The state component holding the current angle.
        state_angle: usize,
        /// The action component holding the commanded angle.
        action_angle: usize,
        /// The change of angle beyond which the action rotates.
        tolerance: f64,
    },
}

/// `x − y` for a component of period `period`, taken the shorter way round (in
/// `[−period/2, period/2]`); the plain difference when `period` is not positive.
#[inline]
pub fn periodic_difference(x: f64, y: f64, period: f64) -> f64 {
    let d = x - y;
    if period > 0.0 {
        d - period * (d / period).round()
    } else {
        d
    }
}

/// The unit-box value `u` of an angle as the two features `(1 + cos 2πu) / 2`,
/// `(1 + sin 2πu) / 2`.
#[inline]
fn angle_features(u: f64) -> [f64; 2] {
    let t = std::f64::consts::TAU * u;
    [0.5 * (1.0 + t.cos()), 0.5 * (1.0 + t.sin())]
}

/// `v` scaled to the unit box by `[low, high]` (0 where the bounds coincide), as
/// [`Space::to_unit`](super::Space::to_unit) computes it.
#[inline]
fn unit(v: f64, low: f64, high: f64) -> f64 {
    let w = high - low;
    if w > 0.0 { (v - low) / w } else { 0.0 }
}

impl FeatureMap {
    /// Number of features.
    pub fn dim(&self) -> usize {
        match self {
            Self::UnitBox {
                state_components,
                action_components,
                action_length,
                prediction_components,
                move_length,
                periodic,
                ..
            } => {
                let angles = state_components
                    .iter()
                    .chain(prediction_components)
                    .filter(|i| periodic.contains(i))
                    .count();
                state_components.len()
                    + action_components.len()
                    + usize::from(*action_length)
                    + prediction_components.len()
                    + usize::from(*move_length)
                    + angles
            }
            Self::KinematicPrediction {
                state_low,
                move_length,
                ..
            } => 3 * state_low.len() + usize::from(*move_length),
            Self::PerMove { moves, .. } => 3 * moves.len(),
            Self::ActionAndRotation { action_low, .. } => action_low.len() + 1,
        }
    }

    /// Whether the features read the model's prediction `ŝ'`, which the caller must then
    /// supply to [`features_into`](Self::features_into).
    pub fn uses_prediction(&self) -> bool {
        matches!(
            self,
            Self::UnitBox { prediction_components, move_length, .. }
                if !prediction_components.is_empty() || *move_length
        )
    }

    /// The state dimension the map reads (`None`: it does not fix it).
    pub fn state_dim(&self) -> Option<usize> {
        match self {
            Self::UnitBox { state_low, .. }
            | Self::KinematicPrediction { state_low, .. }
            | Self::PerMove { state_low, .. } => Some(state_low.len()),
            Self::ActionAndRotation { .. } => None,
        }
    }

    /// The action dimension the map reads (`None`: it does not fix it).
    pub fn action_dim(&self) -> Option<usize> {
        match self {
            Self::UnitBox { action_low, .. }
            | Self::KinematicPrediction { action_low, .. }
            | Self::ActionAndRotation { action_low, .. } => Some(action_low.len()),
            Self::PerMove { moves, .. } => moves.first().map(Vec::len),
        }
    }

    /// Checks that the map can be evaluated on states of `state_dim` and actions of
    /// `action_dim` components: bounds as long as the spaces, finite and ordered, indices in
    /// range, moves of the action's length. The error is `(field, reason)`, the field relative
    /// to the map (`state_components[2]`).
    pub fn check(&self, state_dim: usize, action_dim: usize) -> Result<(), (String, String)> {
        let err = |f: &str, r: String| Err((f.to_string(), r));
        let bounds = |lo_name: &str, lo: &[f64], hi: &[f64], n: usize| {
            if lo.len() != n || hi.len() != n {
                return Err((
                    lo_name.to_string(),
                    format!(
                        "expected {n} lower and upper bounds, got {} and {}",
                        lo.len(),
                        hi.len()
                    ),
                ));
            }
            match lo
                .iter()
                .zip(hi)
                .position(|(l, h)| !(l.is_finite() && h.is_finite() && l <= h))
            {
                Some(i) => Err((
                    format!("{lo_name}[{i}]"),
                    "bounds must be finite with low <= high".to_string(),
                )),
                None => Ok(()),
            }
        };
        let indices = |name: &str, idx: &[usize], n: usize| match idx.iter().position(|&i| i >= n) {
            Some(k) => Err((
                format!("{name}[{k}]"),
                format!("index {} is not a component (there are {n})", idx[k]),
            )),
            None => Ok(()),
        };
        match self {
            Self::UnitBox {
                state_low,
                state_high,
                action_low,
                action_high,
                state_components,
                action_components,
                action_length,
                prediction_components,
                weights,
                move_length,
                periodic,
            } => {
                bounds("state_low", state_low, state_high, state_dim)?;
                indices("periodic", periodic, state_dim)?;
                bounds("action_low", action_low, action_high, action_dim)?;
                indices("state_components", state_components, state_dim)?;
                indices("action_components", action_components, action_dim)?;
                indices("prediction_components", prediction_components, state_dim)?;
                if *move_length
                    && (weights.len() != state_dim
                        || weights.iter().any(|w| !(w.is_finite() && *w >= 0.0)))
                {
                    return err(
                        "weights",
                        format!("the move's length needs {state_dim} finite weights >= 0"),
                    );
                }
                if self.dim() == 0 {
                    return err("state_components", "no component feeds the features".into());
                }
                if *action_length && action_components.is_empty() {
                    return err(
                        "action_length",
                        "the action's length needs at least one action component".into(),
                    );
                }
            }
            Self::KinematicPrediction {
                state_low,
                state_high,
                action_low,
                action_high,
                ..
            } => {
                bounds("state_low", state_low, state_high, state_dim)?;
                bounds("action_low", action_low, action_high, action_dim)?;
                if state_dim != action_dim {
                    return err(
                        "action_low",
                        format!(
                            "the prediction s + a needs actions of the state's {state_dim} \
                             components, got {action_dim}"
                        ),
                    );
                }
                if state_dim == 0 {
                    return err("state_low", "no component feeds the features".into());
                }
            }
            Self::PerMove {
                state_low,
                state_high,
                moves,
                tolerance,
            } => {
                bounds("state_low", state_low, state_high, state_dim)?;
                if moves.is_empty() {
                    return err("moves", "at least one move".into());
                }
                if let Some(k) = moves
                    .iter()
                    .position(|m| m.len() != action_dim || m.iter().any(|v| !v.is_finite()))
                {
                    return err(
                        &format!("moves[{k}]"),
                        format!("a move is {action_dim} finite numbers"),
                    );
                }
                if !(tolerance.is_finite() && *tolerance >= 0.0) {
                    return err("tolerance", "must be a finite number >= 0".into());
                }
            }
            Self::ActionAndRotation {
                action_low,
                action_high,
                state_angle,
                action_angle,
                tolerance,
            } => {
                bounds("action_low", action_low, action_high, action_dim)?;
                indices("state_angle", &[*state_angle], state_dim)?;
                indices("action_angle", &[*action_angle], action_dim)?;
                if !(tolerance.is_finite() && *tolerance >= 0.0) {
                    return err("tolerance", "must be a finite number >= 0".into());
                }
            }
        }
        Ok(())
    }

    /// `φ(s, a)` into `out` (cleared first), `s_pred` the model's prediction `f̂(s, a)` when
    /// the map [uses it](Self::uses_prediction) (ignored otherwise; a prediction of the wrong
    /// length gives NaN features, which no model trusts). `s` and `a` must have the dimensions
    /// the map was checked for ([`check`](Self::check)); shorter vectors panic on indexing.
    pub fn features_into(&self, s: &[f64], a: &[f64], s_pred: &[f64], out: &mut Vec<f64>) {
        out.clear();
        match self {
            Self::UnitBox {
                state_low,
                state_high,
                action_low,
                action_high,
                state_components,
                action_components,
                action_length,
                prediction_components,
                weights,
                move_length,
                periodic,
            } => {
                let component = |out: &mut Vec<f64>, v: &[f64], i: usize| {
                    let u = unit(v[i], state_low[i], state_high[i]);
                    if periodic.contains(&i) {
                        out.extend(angle_features(u));
                    } else {
                        out.push(u);
                    }
                };
                for &i in state_components {
                    component(out, s, i);
                }
                out.extend(
                    action_components
                        .iter()
                        .map(|&i| unit(a[i], action_low[i], action_high[i])),
                );
                if *action_length {
                    out.push(action_length_fraction(
                        a,
                        action_components,
                        action_low,
                        action_high,
                    ));
                }
                if prediction_components.is_empty() && !*move_length {
                    return;
                }
                if s_pred.len() != s.len() {
                    out.resize(self.dim(), f64::NAN);
                    return;
                }
                for &i in prediction_components {
                    component(out, s_pred, i);
                }
                if *move_length {
                    out.push(weighted_move_fraction(
                        s, s_pred, weights, state_low, state_high, periodic,
                    ));
                }
            }
            Self::KinematicPrediction {
                state_low,
                state_high,
                action_low,
                action_high,
                move_length,
            } => {
                let state = state_low.iter().zip(state_high);
                out.extend(
                    s.iter()
                        .zip(state.clone())
                        .map(|(v, (lo, hi))| unit(*v, *lo, *hi)),
                );
                out.extend(
                    a.iter()
                        .zip(action_low.iter().zip(action_high))
                        .map(|(v, (lo, hi))| unit(*v, *lo, *hi)),
                );
                out.extend(
                    s.iter()
                        .zip(a)
                        .zip(state)
                        .map(|((x, d), (lo, hi))| unit((x + d).clamp(*lo, *hi), *lo, *hi)),
                );
                if *move_length {
                    out.push(predicted_move_fraction(
                        s,
                        a,
                        state_low,
                        state_high,
                        action_low,
                        action_high,
                    ));
                }
            }
            Self::PerMove {
                state_low,
                state_high,
                moves,
                tolerance,
            } => {
                let k = move_index(moves, a, *tolerance).unwrap_or(0);
                out.resize(3 * moves.len(), 0.0);
                for (i, (lo, hi)) in state_low.iter().zip(state_high).enumerate().take(2) {
                    out[2 * k + i] = unit(s[i], *lo, *hi);
                }
                out[2 * moves.len() + k] = 1.0;
            }
            Self::ActionAndRotation {
                action_low,
                action_high,
                state_angle,
                action_angle,
                tolerance,
            } => {
                out.extend(
                    a.iter()
                        .zip(action_low.iter().zip(action_high))
                        .map(|(v, (lo, hi))| unit(*v, *lo, *hi).clamp(0.0, 1.0)),
                );
                let rotates = (a[*action_angle] - s[*state_angle]).abs() > *tolerance;
                out.push(if rotates { 1.0 } else { 0.0 });
            }
        }
    }

    /// `φ(s, a)` (see [`features_into`](Self::features_into)).
    pub fn features(&self, s: &[f64], a: &[f64], s_pred: &[f64]) -> Vec<f64> {
        let mut out = Vec::with_capacity(self.dim());
        self.features_into(s, a, s_pred, &mut out);
        out
    }
}

/// The length of a predicted move `d(ŝ', s)` in a weighted Euclidean distance, as a fraction of
/// the state box's diagonal in the same distance, `d(high, low)` (0 when that is 0): in
/// `[0, 1]` for predictions within the bounds. A model's error often grows with how far it says
/// the robot goes, whatever the command's units; this feature carries it in one input. The
/// `periodic` components' differences take the shorter way round ([`periodic_difference`]).
pub fn weighted_move_fraction(
    s: &[f64],
    s_pred: &[f64],
    weights: &[f64],
    state_low: &[f64],
    state_high: &[f64],
    periodic: &[usize],
) -> f64 {
    let diagonal = weights
        .iter()
        .zip(state_high.iter().zip(state_low))
        .map(|(w, (p, q))| w * (p - q) * (p - q))
        .sum::<f64>()
        .sqrt();
    let moved = (0..weights.len())
        .map(|i| {
            let d = if periodic.contains(&i) {
                periodic_difference(s_pred[i], s[i], state_high[i] - state_low[i])
            } else {
                s_pred[i] - s[i]
            };
            weights[i] * d * d
        })
        .sum::<f64>()
        .sqrt();
    if diagonal > 0.0 {
        moved / diagonal
    } else {
        0.0
    }
}

/// The length of the move a kinematic model predicts, `‖clip(s + a) − s‖` (Euclidean, the
/// prediction clamped to `[state_low, state_high]`), as a fraction of the longest move an action
/// can command, `‖(max(|action_low_i|, |action_high_i|))_i‖` (0 when every action bound is 0):
/// in `[0, 1]` for actions within their bounds. An inaccurate model's error often grows with the
/// size of the move it predicts (a robot that slides on, turns or sags by a share of each
/// move): over `(s, a)` that is a cone around `a = 0`, which a stationary kernel follows only
/// with short length scales; this feature makes it one smooth direction.
pub fn predicted_move_fraction(
    s: &[f64],
    a: &[f64],
    state_low: &[f64],
    state_high: &[f64],
    action_low: &[f64],
    action_high: &[f64],
) -> f64 {
    let moved: f64 = s
        .iter()
        .zip(a)
        .zip(state_low.iter().zip(state_high))
        .map(|((x, d), (lo, hi))| ((x + d).clamp(*lo, *hi) - x).powi(2))
        .sum();
    let longest: f64 = action_low
        .iter()
        .zip(action_high)
        .map(|(lo, hi)| lo.abs().max(hi.abs()).powi(2))
        .sum();
    if longest > 0.0 {
        (moved / longest).sqrt()
    } else {
        0.0
    }
}

/// The length of the action components `components` of `a`, each over the largest magnitude
/// its bounds allow (`max(|low_i|, |high_i|)`, a component with both bounds 0 counting 0), as
/// the root mean square over the components, clamped to `[0, 1]`: `0` for no command, `1` for
/// the longest command in every listed component. Unit-free, so components in different units
/// weigh alike. Where a model's error grows with the size of the command, this one input
/// carries what an ARD kernel would otherwise need short length scales in every action
/// component for.
pub fn action_length_fraction(
    a: &[f64],
    components: &[usize],
    action_low: &[f64],
    action_high: &[f64],
) -> f64 {
    if components.is_empty() {
        return 0.0;
    }
    let sum: f64 = components
        .iter()
        .map(|&i| {
            let r = action_low[i].abs().max(action_high[i].abs());
            if r > 0.0 { (a[i] / r).powi(2) } else { 0.0 }
        })
        .sum();
    (sum / components.len() as f64).sqrt().min(1.0)
}

/// The index of the move within `tolerance` of `a` in every component, if any.
pub fn move_index(moves: &[Vec<f64>], a: &[f64], tolerance: f64) -> Option<usize> {
    moves.iter().position(|m| {
        m.len() == a.len() && m.iter().zip(a).all(|(p, q)| (p - q).abs() <= tolerance)
    })
}

#[cfg(test)]
mod tests {
    use super::super::{
        CustomDomain, CustomParams, Domain, GridFeatures, IcyGridworld, Kinematic,
        KinematicFeatures, KinematicParams, LinearModel, Space, WaterPlant,
    };
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use std::sync::Arc;

    /// A domain's features and its map's agree to the bit on its own random state-actions
    /// (and on points a little outside the bounds, which the map does not clamp either).
    fn agree(d: &dyn Domain) {
        let map = d.feature_map();
        let (n, m) = (d.state_space().dim(), d.action_space().dim());
        map.check(n, m).expect("the map checks");
        assert_eq!(map.dim(), d.feature_dim());
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..500 {
            let s = d.sample_state(&mut rng);
            let a = d.sample_action(&s, &mut rng);
            let (want, got) = (d.features(&s, &a, &[]), map.features(&s, &a, &[]));
            assert_eq!(
                want.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                got.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                "{} at s = {s:?}, a = {a:?}",
                d.kind()
            );
        }
    }

    #[test]
    fn every_built_in_domain_computes_its_maps_features() {
        agree(&IcyGridworld::default_layout());
        agree(&IcyGridworld::default_layout().with_features(GridFeatures::PerMove));
        for features in [
            KinematicFeatures::StateAction,
            KinematicFeatures::StateActionPrediction,
            KinematicFeatures::StateActionPredictionLength,
        ] {
            agree(
                &Kinematic::new(KinematicParams {
                    features,
                    ..KinematicParams::default()
                })
                .unwrap(),
            );
            agree(
                &Kinematic::new(KinematicParams {
                    state_low: vec![-2.0, 0.0, 1.0],
                    state_high: vec![2.0, 0.5, 1.25],
                    action_low: vec![-0.3, -0.1, 0.0],
                    action_high: vec![0.3, 0.1, 0.05],
                    features,
                    ..KinematicParams::default()
                })
                .unwrap(),
            );
        }
        agree(&WaterPlant::default());
        let space = |n: usize, lo: f64, hi: f64| Space {
            names: (0..n).map(|i| format!("c{i}")).collect(),
            low: vec![lo; n],
            high: vec![hi; n],
            values: None,
        };
        let params = CustomParams {
            state: space(4, -1.0, 3.0),
            // An angle among the features: two of them, cos and sin.
            periodic: vec![2],
            action: space(2, -0.5, 0.5),
            feature_state: vec![2, 0],
            feature_action: vec![1],
            action_length: true,
            feature_prediction: vec![],
            move_length: false,
            weights: vec![1.0; 4],
            goal_components: vec![0],
            goal_radius: vec![0.1],
            obstacles: Vec::new(),
            steer_samples: 4,
            rollout_length: Some(10),
        };
        let model = LinearModel::new(
            vec![vec![0.0; 4]; 4],
            vec![vec![0.0; 2]; 4],
            vec![0.0; 4],
            &params.state,
            &params.action,
        )
        .unwrap();
        agree(&CustomDomain::new(params, Arc::new(model)).unwrap());
    }

    #[test]
    fn the_move_length_is_the_predicted_moves_share_of_the_longest_one() {
        let d = Kinematic::new(KinematicParams {
            features: KinematicFeatures::StateActionPredictionLength,
            action_low: vec![-0.1, -0.2],
            action_high: vec![0.3, 0.2],
            ..KinematicParams::default()
        })
        .unwrap();
        let length = |s: &[f64], a: &[f64]| *d.features(s, a, &[]).last().unwrap();
        // The longest commandable move is (0.3, 0.2); the feature is its share.
        assert!((length(&[0.5, 0.5], &[0.3, 0.2]) - 1.0).abs() < 1e-12);
        assert!((length(&[0.5, 0.5], &[-0.1, 0.0]) - 0.1 / 0.13f64.sqrt()).abs() < 1e-12);
        assert_eq!(length(&[0.5, 0.5], &[0.0, 0.0]), 0.0);
        // A move into the state bounds is clipped: the model predicts a shorter one.
        assert_eq!(length(&[1.0, 0.5], &[0.3, 0.0]), 0.0);
        assert!((length(&[0.9, 0.5], &[0.3, 0.0]) - 0.1 / 0.13f64.sqrt()).abs() < 1e-12);
        assert_eq!(d.feature_dim(), 7);
        assert_eq!(d.feature_names()[6], "predicted_move_length");
    }

    #[test]
    fn the_action_length_weighs_each_component_by_its_own_bounds() {
        // Components in different units: a push of 0.05 m of 0.1 m, a turn of 1 rad of 2 rad.
        let (low, high) = ([-0.1, -2.0, 0.0], [0.1, 1.0, 3.0]);
        let f = |a: &[f64], c: &[usize]| action_length_fraction(a, c, &low, &high);
        assert!((f(&[0.05, 1.0, 9.0], &[0, 1]) - 0.5).abs() < 1e-12);
        assert!((f(&[-0.1, -2.0, 0.0], &[0, 1]) - 1.0).abs() < 1e-12);
        assert_eq!(f(&[0.0, 0.0, 3.0], &[0, 1]), 0.0);
        assert!((f(&[0.0, 0.0, 3.0], &[2]) - 1.0).abs() < 1e-12);
        // Beyond the bounds it is clamped; no component, no length.
        assert_eq!(f(&[0.0, 0.0, 6.0], &[2]), 1.0);
        assert_eq!(f(&[0.1, 0.0, 0.0], &[]), 0.0);
        let map = FeatureMap::UnitBox {
            state_low: vec![0.0],
            state_high: vec![1.0],
            action_low: low.to_vec(),
            action_high: high.to_vec(),
            state_components: vec![0],
            action_components: vec![],
            action_length: true,
            prediction_components: vec![],
            weights: vec![],
            move_length: false,
            periodic: vec![],
        };
        assert_eq!(map.check(1, 3).unwrap_err().0, "action_length");
    }

    #[test]
    fn per_move_features_find_a_move_within_the_tolerance() {
        let g = IcyGridworld::default_layout().with_features(GridFeatures::PerMove);
        let exact = g.features(&[3.0, 4.0], &[-1.0, 0.0], &[]);
        let near = g.features(&[3.0, 4.0], &[-1.0 + 1e-12, 0.0], &[]);
        assert_eq!(
            exact, near,
            "a validated action one rounding away is the same move"
        );
        assert_eq!(exact[4 * 2 + 1], 1.0, "left is move 1");
    }

    #[test]
    fn a_map_that_does_not_fit_the_spaces_is_refused_by_field() {
        let map = FeatureMap::UnitBox {
            state_low: vec![0.0, 0.0],
            state_high: vec![1.0, 1.0],
            action_low: vec![-1.0],
            action_high: vec![1.0],
            state_components: vec![0, 2],
            action_components: vec![0],
            action_length: false,
            prediction_components: vec![],
            weights: vec![],
            move_length: false,
            periodic: vec![],
        };
        assert_eq!(map.check(2, 1).unwrap_err().0, "state_components[1]");
        assert_eq!(map.check(3, 1).unwrap_err().0, "state_low");
        let map = FeatureMap::ActionAndRotation {
            action_low: vec![0.0, 0.0],
            action_high: vec![1.0, f64::NAN],
            state_angle: 0,
            action_angle: 1,
            tolerance: 1e-6,
        };
        assert_eq!(map.check(1, 2).unwrap_err().0, "action_low[1]");
    }
}
