//! A dynamics model served by the robot's own process over HTTP, the operator's list of where
//! such models may live, and the bounds on calling them.
//!
//! **Protocol.** The service sends `POST <url>` with `{"states": [[...]], "actions": [[...]]}`
//! (many points per call) and expects `200` with `{"next_states": [[...]]}` and optionally
//! `"valid": [true, ...]` (the robot's own constraint check: collisions, joint limits). A model
//! that does not answer within its deadline, refuses the connection, answers another status,
//! the wrong shape or non-finite numbers is a [`DynamicsError`] naming its URL; the caller
//! stores nothing.
//!
//! **Binary arrays, by handshake.** Before its first call the service asks `GET <url>`; a model
//! that answers `{"precond_model": 1, "encodings": ["f64le", ...], "state_dim"?: n,
//! "action_dim"?: m}` is called with raw little-endian arrays instead of JSON
//! ([`F64LE_CONTENT_TYPE`]): the states then the actions, row-major, with the header
//! `x-precond-shape: points,n,m`; it answers the next states the same way, optionally followed
//! by one byte (0 or 1) of validity per point. Declared dimensions are checked against the
//! domain's (a mismatch is an error naming both). Any other answer to the `GET` (`404`, `405`,
//! another body) means JSON, which stays the protocol of every model that does not ask for
//! more; an unreachable model is asked again at its next call.
//!
//! - [`policy`]: which URLs may be called ([`ModelUrlPolicy`]), checked at creation and again
//!   at every call, in the one normalised form that is also what the client requests.
//! - [`calls`]: how many calls run at once, how long one may take, and the threads they run on
//!   ([`ModelCalls`], [`ModelCallLimits`]).
//! - [`answer`]: the answer parsed from the stream within what was asked (rows = points sent,
//!   width = the state's dimension).
//!
//! Batches larger than [`MAX_POINTS_PER_CALL`] are split; one keep-alive connection pool per
//! model.

pub mod answer;
pub mod calls;
pub mod policy;

pub use calls::{MAX_TIMEOUT_MS, ModelCallLimits, ModelCalls};
pub use policy::ModelUrlPolicy;

use crate::budget::Budget;
use crate::domain::{Awaited, DynamicsError, DynamicsModel, Predicted};
use answer::AnswerSeed;
use calls::{Permits, block_until, busy, starts_too_late};
use serde::{Deserialize, Serialize};
use std::io::Read;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

/// Most points sent in one call; larger batches are split.
pub const MAX_POINTS_PER_CALL: usize = 4096;
/// Largest accepted response body.
const MAX_RESPONSE_BYTES: u64 = 64 * 1024 * 1024;
/// Bytes of a refused answer's body read to show in the error.
const ERROR_SNIPPET_BYTES: u64 = 4096;
/// RRT edges proposed per round for a remote model: a round's predictions go in one call.
const ROUND_SIZE: usize = 64;
/// Stack of a call thread: the parse is iterative and its nesting bounded by serde_json.
const CALL_THREAD_STACK: usize = 512 * 1024;
/// Content type of the binary encoding: raw little-endian `f64` arrays (see the module docs).
pub const F64LE_CONTENT_TYPE: &str = "application/x-precond-f64le";
/// Longest wait for a model's answer to the handshake (within the call's own deadline).
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(2);
/// Largest handshake answer read.
const MAX_HANDSHAKE_BYTES: u64 = 64 * 1024;

/// How the service and a model exchange arrays, as their handshake settled it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Encoding {
    /// `{"states", "actions"}` → `{"next_states", "valid"?}`: every model's.
    Json,
    /// Raw little-endian `f64` arrays ([`F64LE_CONTENT_TYPE`]).
    F64Le,
}

/// What a model says of itself at `GET <url>`.
#[derive(Debug, Deserialize)]
struct Handshake {
    /// The protocol's version: 1.
    precond_model: u32,
    /// Encodings it reads and answers in, e.g. `["f64le", "json"]`.
    #[serde(default)]
    encodings: Vec<String>,
    /// The state's dimension, when it says.
    state_dim: Option<usize>,
    /// The action's dimension, when it says.
    action_dim: Option<usize>,
}

/// The body the service sends.
#[derive(Debug, Serialize)]
struct PredictRequest<'a> {
    states: &'a [&'a [f64]],
    actions: &'a [&'a [f64]],
}

/// What a call thread needs of its model.
#[derive(Debug)]
struct Inner {
    /// The URL as stored.
    url: String,
    /// Declared time limit of one call.
    timeout_ms: u64,
    state_dim: usize,
    agent: ureq::Agent,
    calls: AtomicU64,
    gate: Arc<ModelCalls>,
    /// The encoding the handshake settled, once it has.
    encoding: OnceLock<Encoding>,
}

/// A dynamics model behind `POST url` (see the module docs).
#[derive(Debug)]
pub struct RemoteModel {
    inner: Arc<Inner>,
}

/// One call, ready to be made: its URL (normalised), points (row-major) and deadline.
struct Call {
    url: String,
    states: Vec<f64>,
    actions: Vec<f64>,
    action_dim: usize,
    n: usize,
    deadline: Instant,
    timeout_ms: u64,
}

impl RemoteModel {
    /// A model at `url` answering next states of dimension `state_dim` within `timeout_ms`
    /// (capped by the operator's limit), called under `gate`'s policy and limits. Nothing is
    /// sent until the first prediction; a URL the policy does not allow (any more) is refused
    /// at every call, with [`DynamicsError::NotAllowed`].
    pub fn new(url: &str, timeout_ms: u64, state_dim: usize, gate: Arc<ModelCalls>) -> Self {
        let agent = ureq::Agent::config_builder()
            .http_status_as_error(false)
            .max_redirects(0)
            .max_idle_connections_per_host(16)
            .user_agent(concat!("precond/", env!("CARGO_PKG_VERSION")))
            .build()
            .into();
        Self {
            inner: Arc::new(Inner {
                url: url.to_string(),
                timeout_ms,
                state_dim,
                agent,
                calls: AtomicU64::new(0),
                gate,
                encoding: OnceLock::new(),
            }),
        }
    }

    /// The model's URL.
    pub fn url(&self) -> &str {
        &self.inner.url
    }

    /// Calls made so far.
    pub fn calls(&self) -> u64 {
        self.inner.calls.load(Ordering::Relaxed)
    }

    /// The time limit of one call: the declared one, capped by the operator's.
    pub fn timeout(&self) -> Duration {
        Duration::from_millis(self.inner.timeout_ms).min(self.inner.gate.limits().max_timeout)
    }

    /// The calls for `states` and `actions`, in chunks of [`MAX_POINTS_PER_CALL`] (their
    /// deadlines set when each is about to start); `NotAllowed` when the policy refuses the URL
    /// now.
    fn prepare(&self, states: &[&[f64]], actions: &[&[f64]]) -> Result<Vec<Call>, DynamicsError> {
        let inner = &self.inner;
        let url = inner
            .gate
            .policy()
            .normalise(&inner.url)
            .map_err(|reason| DynamicsError::NotAllowed {
                model: inner.url.clone(),
                reason,
            })?;
        let timeout = self.timeout();
        let action_dim = actions.first().map_or(0, |a| a.len());
        if let Some(a) = actions.iter().find(|a| a.len() != action_dim) {
            return Err(inner.unavailable(format!(
                "actions of {} and {action_dim} numbers in one call",
                a.len()
            )));
        }
        if let Some(s) = states.iter().find(|s| s.len() != inner.state_dim) {
            return Err(inner.unavailable(format!(
                "a state of {} numbers for a model of {}",
                s.len(),
                inner.state_dim
            )));
        }
        Ok(states
            .chunks(MAX_POINTS_PER_CALL)
            .zip(actions.chunks(MAX_POINTS_PER_CALL))
            .map(|(s, a)| Call {
                url: url.clone(),
                states: s.concat(),
                actions: a.concat(),
                action_dim,
                n: s.len(),
                deadline: Instant::now() + timeout,
                timeout_ms: timeout.as_millis() as u64,
            })
            .collect())
    }

    /// Predicts from an async task (an ingest): waits for permits and the answer without
    /// holding any thread, then the call runs on its own thread.
    pub async fn predict_async(
        &self,
        states: &[&[f64]],
        actions: &[&[f64]],
    ) -> Result<Vec<Predicted>, DynamicsError> {
        let mut out = Vec::with_capacity(states.len());
        for mut call in self.prepare(states, actions)? {
            let begun = Instant::now();
            call.deadline = begun + self.timeout();
            let until = tokio::time::Instant::from_std(call.deadline);
            let permits =
                match tokio::time::timeout_at(until, self.inner.gate.permits(&call.url)).await {
                    Ok(Some(p)) if !starts_too_late(begun, Instant::now(), call.deadline) => p,
                    _ => return Err(busy(&self.inner.url, self.inner.gate.limits())),
                };
            let answer = self.start(call, permits)?;
            // The thread ends by the deadline; a little slack for it to say so.
            let grace = until + Duration::from_secs(1);
            match tokio::time::timeout_at(grace, answer).await {
                Ok(Ok(predicted)) => out.extend(predicted?),
                _ => return Err(self.inner.timed_out()),
            }
        }
        Ok(out)
    }

    /// Starts `call` on a thread of its own, which holds `permits` until it ends.
    fn start(
        &self,
        call: Call,
        permits: Permits,
    ) -> Result<tokio::sync::oneshot::Receiver<Result<Vec<Predicted>, DynamicsError>>, DynamicsError>
    {
        let (tx, rx) = tokio::sync::oneshot::channel();
        let inner = self.inner.clone();
        std::thread::Builder::new()
            .name("precond-model".into())
            .stack_size(CALL_THREAD_STACK)
            .spawn(move || {
                let _permits = permits;
                let _ = tx.send(inner.call(call));
            })
            .map_err(|e| {
                self.inner
                    .unavailable(format!("could not start a call: {e}"))
            })?;
        Ok(rx)
    }
}

impl Inner {
    fn unavailable(&self, reason: impl Into<String>) -> DynamicsError {
        DynamicsError::Unavailable {
            model: self.url.clone(),
            reason: reason.into(),
        }
    }

    fn timed_out(&self) -> DynamicsError {
        DynamicsError::Timeout {
            model: self.url.clone(),
            timeout_ms: Duration::from_millis(self.timeout_ms)
                .min(self.gate.limits().max_timeout)
                .as_millis() as u64,
        }
    }

    /// The encoding to call this model in: the handshake's, asked for now (within
    /// [`HANDSHAKE_TIMEOUT`] and the call's deadline) if no answer settled it yet. A model that
    /// could not be reached is asked again next time; this call then goes as JSON (and will
    /// most likely fail the same way, naming the model).
    fn encoding(&self, call: &Call) -> Result<Encoding, DynamicsError> {
        if let Some(e) = self.encoding.get() {
            return Ok(*e);
        }
        let left = call.deadline.saturating_duration_since(Instant::now());
        let asked = self
            .agent
            .get(&call.url)
            .config()
            .timeout_global(Some(left.min(HANDSHAKE_TIMEOUT)))
            .build()
            .header("accept", "application/json")
            .call();
        let Ok(response) = asked else {
            return Ok(Encoding::Json);
        };
        let settled = if response.status().as_u16() != 200 {
            Encoding::Json
        } else {
            let mut body = Vec::new();
            let read = response
                .into_body()
                .into_reader()
                .take(MAX_HANDSHAKE_BYTES)
                .read_to_end(&mut body);
            match read
                .ok()
                .and_then(|_| serde_json::from_slice::<Handshake>(&body).ok())
            {
                Some(h) if h.precond_model == 1 => {
                    self.check_declared(&h, call.action_dim)?;
                    if h.encodings.iter().any(|e| e == "f64le") {
                        Encoding::F64Le
                    } else {
                        Encoding::Json
                    }
                }
                _ => Encoding::Json,
            }
        };
        Ok(*self.encoding.get_or_init(|| settled))
    }

    /// A model that declares dimensions other than the domain's is refused, naming both.
    fn check_declared(&self, h: &Handshake, action_dim: usize) -> Result<(), DynamicsError> {
        if let Some(n) = h.state_dim.filter(|&n| n != self.state_dim) {
            return Err(self.unavailable(format!(
                "declares states of {n} numbers; the domain's state has {}",
                self.state_dim
            )));
        }
        if let Some(m) = h.action_dim.filter(|&m| m != action_dim) {
            return Err(self.unavailable(format!(
                "declares actions of {m} numbers; the domain's action has {action_dim}"
            )));
        }
        Ok(())
    }

    /// One HTTP exchange, on a call thread, ending by `call.deadline`.
    fn call(&self, call: Call) -> Result<Vec<Predicted>, DynamicsError> {
        self.calls.fetch_add(1, Ordering::Relaxed);
        if call.deadline <= Instant::now() {
            return Err(self.timed_out());
        }
        let encoding = self.encoding(&call)?;
        let response = self.send(&call, encoding)?;
        let answer = self.read(response, &call)?;
        let valid = answer.valid.unwrap_or_else(|| vec![true; call.n]);
        Ok(answer
            .next_states
            .into_iter()
            .zip(valid)
            .map(|(next, valid)| Predicted { next, valid })
            .collect())
    }

    /// The timeout of `call`, as an error.
    fn call_timed_out(&self, call: &Call) -> DynamicsError {
        DynamicsError::Timeout {
            model: self.url.clone(),
            timeout_ms: call.timeout_ms,
        }
    }

    /// Sends `call`'s points in `encoding` and waits for the answer's head, until its deadline.
    fn send(
        &self,
        call: &Call,
        encoding: Encoding,
    ) -> Result<ureq::http::Response<ureq::Body>, DynamicsError> {
        let left = call.deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(self.timed_out());
        }
        let request = self
            .agent
            .post(&call.url)
            .config()
            .timeout_global(Some(left))
            .build();
        let sent = match encoding {
            Encoding::Json => {
                let body = serde_json::to_vec(&PredictRequest {
                    states: &rows(&call.states, call.n, self.state_dim),
                    actions: &rows(&call.actions, call.n, call.action_dim),
                })
                .map_err(|e| self.unavailable(format!("could not encode the request: {e}")))?;
                request
                    .header("content-type", "application/json")
                    .send(&body[..])
            }
            Encoding::F64Le => {
                let mut body = Vec::with_capacity(8 * (call.states.len() + call.actions.len()));
                for v in call.states.iter().chain(&call.actions) {
                    body.extend_from_slice(&v.to_le_bytes());
                }
                let shape = format!("{},{},{}", call.n, self.state_dim, call.action_dim);
                request
                    .header("content-type", F64LE_CONTENT_TYPE)
                    .header("x-precond-shape", &shape)
                    .send(&body[..])
            }
        };
        match sent {
            Ok(r) => Ok(r),
            Err(ureq::Error::Timeout(_)) => Err(self.call_timed_out(call)),
            Err(e) => Err(self.unavailable(format!("could not be called: {e}"))),
        }
    }

    /// The answer to `call`, read within [`MAX_RESPONSE_BYTES`] and checked: binary when the
    /// model says so in its content type, JSON otherwise; another status than 2xx is an error
    /// showing the start of its body.
    fn read(
        &self,
        response: ureq::http::Response<ureq::Body>,
        call: &Call,
    ) -> Result<answer::Answer, DynamicsError> {
        let status = response.status().as_u16();
        let binary = response
            .headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok())
            .is_some_and(|v| v.starts_with(F64LE_CONTENT_TYPE));
        let mut reader = response.into_body().into_reader();
        if !(200..300).contains(&status) {
            let mut body = Vec::new();
            let _ = (&mut reader)
                .take(ERROR_SNIPPET_BYTES)
                .read_to_end(&mut body);
            let text = String::from_utf8_lossy(&body);
            let snippet: String = text.chars().take(300).collect();
            return Err(self.unavailable(format!("answered HTTP {status}: {snippet}")));
        }
        let counted = Counted {
            inner: reader,
            left: MAX_RESPONSE_BYTES,
        };
        let too_large =
            || self.unavailable(format!("answered more than {MAX_RESPONSE_BYTES} bytes"));
        if binary {
            return answer::parse_f64le(counted, call.n, self.state_dim).map_err(|e| match e {
                answer::BinaryError::Read(e) => match e.kind() {
                    std::io::ErrorKind::TimedOut => self.call_timed_out(call),
                    std::io::ErrorKind::FileTooLarge => too_large(),
                    _ => self.unavailable(format!("answer could not be read: {e}")),
                },
                answer::BinaryError::Shape(reason) => self.unavailable(reason),
            });
        }
        let seed = AnswerSeed {
            n: call.n,
            dim: self.state_dim,
        };
        answer::parse(std::io::BufReader::new(counted), seed).map_err(|e| match e.io_error_kind() {
            Some(std::io::ErrorKind::TimedOut) => self.call_timed_out(call),
            Some(std::io::ErrorKind::FileTooLarge) => too_large(),
            Some(_) => self.unavailable(format!("answer could not be read: {e}")),
            None => self.unavailable(format!(
                "answered something other than {{\"next_states\": [[...] × {}], \
                 \"valid\"?: [...]}} with finite numbers: {e}",
                call.n
            )),
        })
    }
}

/// `n` rows of `dim` numbers each of the row-major `flat`.
fn rows(flat: &[f64], n: usize, dim: usize) -> Vec<&[f64]> {
    (0..n).map(|i| &flat[i * dim..(i + 1) * dim]).collect()
}

/// A reader that fails with `FileTooLarge` past `left` bytes.
struct Counted<R> {
    inner: R,
    left: u64,
}

impl<R: Read> Read for Counted<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        if self.left == 0 {
            // One more byte tells a body of exactly the limit from a longer one.
            let mut probe = [0u8; 1];
            return match self.inner.read(&mut probe)? {
                0 => Ok(0),
                _ => Err(std::io::ErrorKind::FileTooLarge.into()),
            };
        }
        let max = buf
            .len()
            .min(usize::try_from(self.left).unwrap_or(usize::MAX));
        let n = self.inner.read(&mut buf[..max])?;
        self.left -= n as u64;
        Ok(n)
    }
}

impl DynamicsModel for RemoteModel {
    fn predict_batch(
        &self,
        states: &[&[f64]],
        actions: &[&[f64]],
    ) -> Result<Vec<Predicted>, DynamicsError> {
        self.predict_batch_within(states, actions, &Budget::unlimited())
    }

    /// Each call's deadline is the earlier of its own and the search's; the wait for it ends
    /// as soon as the search is cancelled.
    fn predict_batch_within(
        &self,
        states: &[&[f64]],
        actions: &[&[f64]],
        budget: &Budget,
    ) -> Result<Vec<Predicted>, DynamicsError> {
        let mut out = Vec::with_capacity(states.len());
        for mut call in self.prepare(states, actions)? {
            let begun = Instant::now();
            let own = begun + self.timeout();
            call.deadline = budget.deadline().map_or(own, |d| d.min(own));
            let deadline = call.deadline;
            let stopped = || budget.stop().is_some();
            let permits = match block_until(self.inner.gate.permits(&call.url), deadline, stopped) {
                Some(Some(p)) if !starts_too_late(begun, Instant::now(), deadline) => p,
                _ if budget.stop().is_some() => return Err(self.inner.timed_out()),
                _ => return Err(busy(&self.inner.url, self.inner.gate.limits())),
            };
            let answer = self.start(call, permits)?;
            let grace = deadline + Duration::from_secs(1);
            match block_until(answer, grace, stopped) {
                Some(Ok(predicted)) => out.extend(predicted?),
                _ => return Err(self.inner.timed_out()),
            }
        }
        Ok(out)
    }

    fn round_size(&self) -> usize {
        ROUND_SIZE
    }

    fn predict_awaitable<'a>(
        &'a self,
        states: &'a [&'a [f64]],
        actions: &'a [&'a [f64]],
    ) -> Option<Awaited<'a>> {
        Some(Box::pin(self.predict_async(states, actions)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn allowing(url: &str) -> Arc<ModelCalls> {
        Arc::new(ModelCalls::new(
            ModelUrlPolicy::new(&[url]).unwrap(),
            ModelCallLimits::default(),
        ))
    }

    #[test]
    fn a_refused_connection_is_a_clear_error_naming_the_model() {
        // A port that was just free: any refusal will do.
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}/predict", listener.local_addr().unwrap());
        drop(listener);
        let m = RemoteModel::new(&url, 500, 2, allowing(&url));
        let e = m.predict_batch(&[&[0.0, 0.0]], &[&[1.0]]).unwrap_err();
        match e {
            DynamicsError::Unavailable { model, .. } => assert_eq!(model, url),
            other => panic!("unexpected {other:?}"),
        }
        assert_eq!(m.calls(), 1);
    }

    #[test]
    fn a_url_the_policy_does_not_allow_is_never_called() {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}/predict", listener.local_addr().unwrap());
        let m = RemoteModel::new(&url, 500, 2, Arc::new(ModelCalls::default()));
        let e = m.predict_batch(&[&[0.0, 0.0]], &[&[1.0]]).unwrap_err();
        assert!(
            matches!(&e, DynamicsError::NotAllowed { model, reason }
                if *model == url && reason.contains("--allow-model-url")),
            "{e:?}"
        );
        assert_eq!(m.calls(), 0);
    }

    #[test]
    fn a_cancelled_search_stops_waiting_for_a_hung_model_at_once() {
        // A model that accepts the connection and never answers.
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}/predict", listener.local_addr().unwrap());
        let m = RemoteModel::new(&url, 60_000, 2, allowing(&url));
        let flag = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let budget = Budget::unlimited().cancelled_by(flag.clone());
        let raise = {
            let flag = flag.clone();
            std::thread::spawn(move || {
                std::thread::sleep(Duration::from_millis(200));
                flag.store(true, Ordering::Relaxed);
            })
        };
        let started = Instant::now();
        let e = m
            .predict_batch_within(&[&[0.0, 0.0]], &[&[1.0]], &budget)
            .unwrap_err();
        raise.join().unwrap();
        assert!(matches!(e, DynamicsError::Timeout { .. }), "{e:?}");
        assert!(
            started.elapsed() < Duration::from_secs(2),
            "{:?}",
            started.elapsed()
        );
        // A search deadline shorter than the model's timeout bounds the call too.
        let started = Instant::now();
        let budget = Budget::until(Instant::now() + Duration::from_millis(300));
        assert!(
            m.predict_batch_within(&[&[0.0, 0.0]], &[&[1.0]], &budget)
                .is_err()
        );
        let took = started.elapsed();
        assert!(
            took >= Duration::from_millis(250) && took < Duration::from_secs(2),
            "{took:?}"
        );
        drop(listener);
    }
}
