//! The token-less loopback server's guard against web pages.
//!
//! Without `--token-file` the server only listens on a loopback address, so only processes of
//! this machine reach it — among them the user's browser, which any web site can make send
//! requests. Two checks close that door when the server has no tokens and is bound to a
//! loopback address:
//!
//! - **Host** (DNS rebinding): a page on `attacker.example` whose name resolves to 127.0.0.1
//!   reads the answers as same-origin. Every request must name this machine in `Host`:
//!   `localhost` (or a `*.localhost` name, which browsers resolve to loopback themselves) or a
//!   loopback address literal (`127.0.0.1`, `[::1]`), with any port. Anything else is `403`.
//! - **Origin** (cross-site writes): a page on another site can post a form or a `text/plain`
//!   body without a CORS preflight. A write (any method but `GET`, `HEAD`, `OPTIONS`) that
//!   carries `Origin` must come from this server's own origin (`http://` + the request's
//!   `Host`, as the dashboard's own calls do) or from an origin the operator allows with
//!   `--cors-allow-origin`; otherwise `403`. Clients that are not browsers (curl, the Python
//!   client, robots) send no `Origin` and are not affected.
//!
//! Bodies must also be declared as JSON (see [`super::extract`]), whatever the configuration.
//! With tokens, none of this is needed: a page cannot add `Authorization` to a cross-site
//! request without a preflight, which is refused, and a rebound name gets no token. The
//! health checks stay open to probes.

use super::error::ApiError;
use axum::extract::Request;
use axum::http::{HeaderMap, Method, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use std::net::IpAddr;
use std::sync::Arc;

/// What the guard allows besides this machine's own names (see the module docs).
#[derive(Debug, Clone, Default)]
pub struct LoopbackGuard {
    /// Origins (`scheme://host[:port]`, lower case, no trailing `/`) allowed to write, as given
    /// by `--cors-allow-origin`.
    pub allowed_origins: Vec<String>,
}

/// The host part of an authority (`host[:port]`, `[v6][:port]`), lower case, without a
/// trailing dot.
fn host_of(authority: &str) -> String {
    let authority = authority.trim();
    let host = if let Some(rest) = authority.strip_prefix('[') {
        rest.split(']').next().unwrap_or_default()
    } else {
        match authority.rsplit_once(':') {
            Some((host, port)) if port.bytes().all(|b| b.is_ascii_digit()) => host,
            _ => authority,
        }
    };
    host.trim_end_matches('.').to_ascii_lowercase()
}

/// Whether `authority` (a `Host` value) names this machine: `localhost`, `*.localhost` or a
/// loopback address.
pub fn is_local_authority(authority: &str) -> bool {
    let host = host_of(authority);
    host == "localhost"
        || host.ends_with(".localhost")
        || host.parse::<IpAddr>().is_ok_and(|ip| ip.is_loopback())
}

impl LoopbackGuard {
    /// `Ok` or the `403` to answer for a request with `method` and `headers` (see the module
    /// docs).
    pub fn check(&self, method: &Method, headers: &HeaderMap) -> Result<(), ApiError> {
        let host = headers
            .get(header::HOST)
            .map(|h| String::from_utf8_lossy(h.as_bytes()).into_owned());
        if let Some(host) = &host
            && !is_local_authority(host)
        {
            return Err(ApiError::Forbidden(format!(
                "this server has no access tokens and answers only requests addressed to this \
                 machine (localhost, 127.0.0.1, [::1]); Host was {host:?}"
            )));
        }
        if matches!(*method, Method::GET | Method::HEAD | Method::OPTIONS) {
            return Ok(());
        }
        let Some(origin) = headers.get(header::ORIGIN) else {
            return Ok(());
        };
        let origin = String::from_utf8_lossy(origin.as_bytes()).to_ascii_lowercase();
        let origin = origin.trim_end_matches('/');
        let own = host.map(|h| format!("http://{}", h.trim().to_ascii_lowercase()));
        if own.as_deref() == Some(origin) || self.allowed_origins.iter().any(|o| o == origin) {
            return Ok(());
        }
        Err(ApiError::Forbidden(format!(
            "a write from the web page at {origin:?} is refused: this server has no access \
             tokens, so only its own pages (and origins allowed with --cors-allow-origin) may \
             write to it"
        )))
    }
}

/// The middleware (installed only on a token-less server bound to a loopback address); the
/// health checks are not guarded.
pub async fn guard(guard: Arc<LoopbackGuard>, req: Request, next: Next) -> Response {
    if super::auth::is_open(req.uri().path()) {
        return next.run(req).await;
    }
    match guard.check(req.method(), req.headers()) {
        Ok(()) => next.run(req).await,
        Err(e) => e.into_response(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;

    fn headers(pairs: &[(&'static str, &str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.insert(*k, HeaderValue::from_str(v).unwrap());
        }
        h
    }

    #[test]
    fn only_this_machines_names_pass_the_host_check() {
        for ok in [
            "127.0.0.1:8080",
            "localhost",
            "LOCALHOST:80",
            "localhost.:8080",
            "dash.localhost:1",
            "[::1]:8080",
            "127.0.0.2",
        ] {
            assert!(is_local_authority(ok), "{ok}");
        }
        for bad in [
            "attacker.example:8080",
            "localhost.attacker.example",
            "127.0.0.1.nip.io",
            "10.0.0.1:8080",
            "[::2]",
            "",
        ] {
            assert!(!is_local_authority(bad), "{bad}");
        }
    }

    #[test]
    fn writes_from_other_origins_are_refused_reads_are_not() {
        let g = LoopbackGuard {
            allowed_origins: vec!["http://lab-pc:8080".into()],
        };
        let post = Method::POST;
        let host = ("host", "127.0.0.1:8080");
        assert!(g.check(&post, &headers(&[host])).is_ok(), "no Origin: curl");
        assert!(
            g.check(
                &post,
                &headers(&[host, ("origin", "http://127.0.0.1:8080")])
            )
            .is_ok()
        );
        assert!(
            g.check(&post, &headers(&[host, ("origin", "http://lab-pc:8080/")]))
                .is_ok()
        );
        for origin in [
            "http://evil.example",
            "null",
            "http://127.0.0.1:3000",
            "http://localhost:8080",
        ] {
            let e = g
                .check(&post, &headers(&[host, ("origin", origin)]))
                .unwrap_err();
            assert_eq!(e.code(), "forbidden", "{origin}");
        }
        assert!(
            g.check(
                &Method::GET,
                &headers(&[host, ("origin", "http://evil.example")])
            )
            .is_ok(),
            "a cross-site read gets no CORS grant, so the page cannot see the answer"
        );
        let e = g
            .check(&Method::GET, &headers(&[("host", "attacker.example:8080")]))
            .unwrap_err();
        assert!(e.to_string().contains("attacker.example"), "{e}");
    }
}
