//! A dynamics model served by the robot's own process over HTTP, and the operator's list of
//! where such models may live.
//!
//! **Protocol.** The service sends `POST <url>` with `{"states": [[...]], "actions": [[...]]}`
//! (many points per call) and expects `200` with `{"next_states": [[...]]}` and optionally
//! `"valid": [true, ...]` (the robot's own constraint check: collisions, joint limits). A model
//! that does not answer within `timeout_ms`, refuses the connection, answers another status, the
//! wrong shape or non-finite numbers is a [`DynamicsError`] naming its URL; the caller stores
//! nothing.
//!
//! Calls are blocking (the planner and the labeller call the model from the blocking pool) and
//! go through one keep-alive connection pool per model. Batches larger than
//! [`MAX_POINTS_PER_CALL`] are split.

use crate::domain::{DynamicsError, DynamicsModel, Predicted};
use reqwest::Url;
use serde::{Deserialize, Serialize};
use std::io::Read;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

/// Most points sent in one call; larger batches are split.
pub const MAX_POINTS_PER_CALL: usize = 4096;
/// Largest accepted response body.
const MAX_RESPONSE_BYTES: u64 = 64 * 1024 * 1024;
/// RRT edges proposed per round for a remote model: a round's predictions go in one call.
const ROUND_SIZE: usize = 64;
/// The longest accepted `timeout_ms`.
pub const MAX_TIMEOUT_MS: u64 = 600_000;

/// Where remote models may live: URL prefixes the operator allows (`--allow-model-url`).
///
/// A URL is allowed when it has the scheme, host and port of an allowed prefix and its path
/// starts with the prefix's path. Nothing is allowed by default.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ModelUrlPolicy {
    prefixes: Vec<Url>,
}

impl ModelUrlPolicy {
    /// A policy allowing `prefixes` (each an `http://` URL, e.g. `http://robot-pc:9000/`).
    pub fn new<S: AsRef<str>>(prefixes: &[S]) -> Result<Self, String> {
        let prefixes = prefixes
            .iter()
            .map(|p| {
                let p = p.as_ref().trim();
                let url = Url::parse(p).map_err(|e| format!("model URL prefix {p:?}: {e}"))?;
                if url.scheme() != "http" || url.host_str().is_none() {
                    return Err(format!(
                        "model URL prefix {p:?} must be an http:// URL with a host"
                    ));
                }
                Ok(url)
            })
            .collect::<Result<_, _>>()?;
        Ok(Self { prefixes })
    }

    /// The allowed prefixes.
    pub fn prefixes(&self) -> Vec<String> {
        self.prefixes.iter().map(Url::to_string).collect()
    }

    /// Whether `url` may be called; the error says why not.
    pub fn check(&self, url: &str) -> Result<(), String> {
        let parsed = Url::parse(url).map_err(|e| format!("not a valid URL: {e}"))?;
        if parsed.scheme() != "http" {
            return Err("only http:// model URLs are supported".into());
        }
        if !parsed.username().is_empty() || parsed.password().is_some() {
            return Err("a model URL may not carry credentials".into());
        }
        let allowed = self.prefixes.iter().any(|p| {
            p.scheme() == parsed.scheme()
                && p.host_str() == parsed.host_str()
                && p.port_or_known_default() == parsed.port_or_known_default()
                && parsed.path().starts_with(p.path())
        });
        if allowed {
            Ok(())
        } else if self.prefixes.is_empty() {
            Err(
                "remote models are not enabled on this server (the operator allows model URLs \
                 with `precond serve --allow-model-url PREFIX`)"
                    .into(),
            )
        } else {
            Err(format!(
                "not under a model URL prefix the operator allows ({})",
                self.prefixes().join(", ")
            ))
        }
    }
}

/// The body the service sends.
#[derive(Debug, Serialize)]
struct PredictRequest<'a> {
    states: &'a [&'a [f64]],
    actions: &'a [&'a [f64]],
}

/// The body a model answers.
#[derive(Debug, Deserialize)]
struct PredictResponse {
    next_states: Vec<Vec<f64>>,
    #[serde(default)]
    valid: Option<Vec<bool>>,
}

/// A dynamics model behind `POST url` (see the module docs).
#[derive(Debug)]
pub struct RemoteModel {
    url: String,
    timeout_ms: u64,
    state_dim: usize,
    agent: ureq::Agent,
    calls: AtomicU64,
}

impl RemoteModel {
    /// A model at `url` answering next states of dimension `state_dim` within `timeout_ms`.
    /// Nothing is sent until the first prediction.
    pub fn new(url: &str, timeout_ms: u64, state_dim: usize) -> Self {
        let agent = ureq::Agent::config_builder()
            .timeout_global(Some(Duration::from_millis(timeout_ms)))
            .http_status_as_error(false)
            .max_redirects(0)
            .max_idle_connections_per_host(16)
            .user_agent(concat!("precond/", env!("CARGO_PKG_VERSION")))
            .build()
            .into();
        Self {
            url: url.to_string(),
            timeout_ms,
            state_dim,
            agent,
            calls: AtomicU64::new(0),
        }
    }

    /// The model's URL.
    pub fn url(&self) -> &str {
        &self.url
    }

    /// Calls made so far.
    pub fn calls(&self) -> u64 {
        self.calls.load(Ordering::Relaxed)
    }

    fn unavailable(&self, reason: impl Into<String>) -> DynamicsError {
        DynamicsError::Unavailable {
            model: self.url.clone(),
            reason: reason.into(),
        }
    }

    fn call(&self, states: &[&[f64]], actions: &[&[f64]]) -> Result<Vec<Predicted>, DynamicsError> {
        self.calls.fetch_add(1, Ordering::Relaxed);
        let n = states.len();
        let sent = self
            .agent
            .post(&self.url)
            .send_json(PredictRequest { states, actions });
        let mut response = match sent {
            Ok(r) => r,
            Err(ureq::Error::Timeout(_)) => {
                return Err(DynamicsError::Timeout {
                    model: self.url.clone(),
                    timeout_ms: self.timeout_ms,
                });
            }
            Err(e) => return Err(self.unavailable(format!("could not be called: {e}"))),
        };
        let status = response.status().as_u16();
        let mut body = Vec::new();
        let read = response
            .body_mut()
            .as_reader()
            .take(MAX_RESPONSE_BYTES + 1)
            .read_to_end(&mut body);
        match read {
            Ok(_) if body.len() as u64 > MAX_RESPONSE_BYTES => {
                return Err(
                    self.unavailable(format!("answered more than {MAX_RESPONSE_BYTES} bytes"))
                );
            }
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {
                return Err(DynamicsError::Timeout {
                    model: self.url.clone(),
                    timeout_ms: self.timeout_ms,
                });
            }
            Err(e) => return Err(self.unavailable(format!("answer could not be read: {e}"))),
        }
        if !(200..300).contains(&status) {
            let text = String::from_utf8_lossy(&body);
            let snippet: String = text.chars().take(300).collect();
            return Err(self.unavailable(format!("answered HTTP {status}: {snippet}")));
        }
        let answer: PredictResponse = serde_json::from_slice(&body).map_err(|e| {
            let text = String::from_utf8_lossy(&body);
            if text.contains("NaN") || text.contains("Infinity") {
                self.unavailable("answered a non-finite number (NaN or Infinity)")
            } else {
                self.unavailable(format!(
                    "answered something other than {{\"next_states\": [[...]], \"valid\"?: [...]}}: {e}"
                ))
            }
        })?;
        if answer.next_states.len() != n {
            return Err(self.unavailable(format!(
                "answered {} next states for {n} points",
                answer.next_states.len()
            )));
        }
        for (i, s) in answer.next_states.iter().enumerate() {
            if s.len() != self.state_dim {
                return Err(self.unavailable(format!(
                    "next_states[{i}] has {} components, the state has {}",
                    s.len(),
                    self.state_dim
                )));
            }
            if s.iter().any(|x| !x.is_finite()) {
                return Err(self.unavailable(format!("next_states[{i}] is not finite")));
            }
        }
        let valid = match answer.valid {
            Some(v) if v.len() != n => {
                return Err(self.unavailable(format!(
                    "answered {} validity flags for {n} points",
                    v.len()
                )));
            }
            Some(v) => v,
            None => vec![true; n],
        };
        Ok(answer
            .next_states
            .into_iter()
            .zip(valid)
            .map(|(next, valid)| Predicted { next, valid })
            .collect())
    }
}

impl DynamicsModel for RemoteModel {
    fn predict_batch(
        &self,
        states: &[&[f64]],
        actions: &[&[f64]],
    ) -> Result<Vec<Predicted>, DynamicsError> {
        let mut out = Vec::with_capacity(states.len());
        for (s, a) in states
            .chunks(MAX_POINTS_PER_CALL)
            .zip(actions.chunks(MAX_POINTS_PER_CALL))
        {
            out.extend(self.call(s, a)?);
        }
        Ok(out)
    }

    fn round_size(&self) -> usize {
        ROUND_SIZE
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_policy_allows_only_what_the_operator_listed() {
        let p = ModelUrlPolicy::new(&["http://robot-pc:9000/models/"]).unwrap();
        assert!(p.check("http://robot-pc:9000/models/arm").is_ok());
        assert!(p.check("http://robot-pc:9000/other").is_err());
        assert!(p.check("http://robot-pc:9001/models/arm").is_err());
        assert!(p.check("http://robot-pc.evil.com:9000/models/arm").is_err());
        assert!(p.check("http://user:pw@robot-pc:9000/models/arm").is_err());
        assert!(p.check("https://robot-pc:9000/models/arm").is_err());
        assert!(p.check("not a url").is_err());
        let default_port = ModelUrlPolicy::new(&["http://robot/"]).unwrap();
        assert!(default_port.check("http://robot:80/predict").is_ok());
        assert!(ModelUrlPolicy::default().check("http://robot/").is_err());
        assert!(ModelUrlPolicy::new(&["ftp://robot/"]).is_err());
    }

    #[test]
    fn a_refused_connection_is_a_clear_error_naming_the_model() {
        // Port 9 on loopback (discard) is closed on this kind of machine; any refusal will do.
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}/predict", listener.local_addr().unwrap());
        drop(listener);
        let m = RemoteModel::new(&url, 500, 2);
        let e = m.predict_batch(&[&[0.0, 0.0]], &[&[1.0]]).unwrap_err();
        match e {
            DynamicsError::Unavailable { model, .. } => assert_eq!(model, url),
            other => panic!("unexpected {other:?}"),
        }
        assert_eq!(m.calls(), 1);
    }
}
