//! Access tokens: who may call which route on which experiment.
//!
//! A token file holds one token a line, `token role [experiment-ids|*]`:
//!
//! ```text
//! # the robot of bench 2 may post and ask in experiments 3 and 4
//! 7f0c…e1  write  3,4
//! # the lab's dashboard reads everything
//! 91ab…42  read   *
//! # the operator
//! c3d2…9a  admin
//! ```
//!
//! Roles are cumulative: `read` calls the GET routes, precondition queries and test-time plans;
//! `write` also everything else that changes an experiment (trajectories, proposals); `admin`
//! also creates experiments, forces refits and excludes (and restores) trajectories. The scope
//! (default `*`) lists the experiments a token may reach; a scoped token cannot create
//! experiments or read `/metrics` (every experiment's totals), and lists only its own
//! experiments.
//!
//! Requests carry `Authorization: Bearer <token>`: none or an unknown token is `401`, a known
//! token without the role or the experiment is `403`. Tokens are compared in constant time
//! (over their SHA-256 digests, so neither content nor length leaks) and never logged: the
//! table's `Debug` shows roles and scopes only. `/healthz` and `/readyz` stay open.

use super::error::ApiError;
use axum::extract::{MatchedPath, Request};
use axum::http::Method;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use sha2::{Digest, Sha256};
use std::collections::BTreeSet;
use std::fmt;
use std::sync::Arc;
use subtle::ConstantTimeEq;

/// Shortest token accepted in a token file: a short token is guessable whatever the compare.
pub const MIN_TOKEN_LEN: usize = 16;

/// What a token may do; each role includes the ones before it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Role {
    /// GET routes, precondition queries, test-time plans.
    Read,
    /// Everything else on an experiment: trajectories, proposals, abandoning.
    Write,
    /// Creating experiments, forcing refits, excluding trajectories from a model.
    Admin,
}

impl Role {
    /// The name used in token files and error messages.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Read => "read",
            Self::Write => "write",
            Self::Admin => "admin",
        }
    }
}

/// The experiments a token reaches.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Scope {
    /// Every experiment, and the server-wide routes (listing, creating, metrics).
    All,
    /// Only these experiments.
    Only(BTreeSet<i64>),
}

impl Scope {
    /// Whether experiment `id` is in scope.
    pub fn allows(&self, id: i64) -> bool {
        match self {
            Self::All => true,
            Self::Only(ids) => ids.contains(&id),
        }
    }
}

/// A known token: the SHA-256 digest of its text, its role and its scope.
#[derive(Clone)]
struct Entry {
    digest: [u8; 32],
    role: Role,
    scope: Scope,
}

/// The caller's identity as established by [`authorize`], put in the request's extensions so
/// that handlers can narrow what they show (e.g. the experiment list).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Caller {
    /// The token's role.
    pub role: Role,
    /// The token's scope.
    pub scope: Scope,
}

/// Who called, for audit records (an exclusion's `created_by`): the first 12 hex digits of
/// the SHA-256 of the caller's token, which an operator computes from the token file
/// (`printf %s "$TOKEN" | sha256sum | cut -c1-12`) and which says nothing usable of the token.
/// Put in the request's extensions beside [`Caller`]; absent on a server without tokens.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Fingerprint(pub String);

impl Fingerprint {
    /// The fingerprint of `token`.
    pub fn of(token: &[u8]) -> Self {
        Self(
            digest(token)[..6]
                .iter()
                .map(|b| format!("{b:02x}"))
                .collect(),
        )
    }
}

/// The tokens of a token file.
#[derive(Clone, Default)]
pub struct TokenTable {
    entries: Vec<Entry>,
}

impl fmt::Debug for TokenTable {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // Never the tokens, not even their digests.
        f.debug_list()
            .entries(self.entries.iter().map(|e| (e.role, &e.scope)))
            .finish()
    }
}

/// Why a token file was refused; names the line.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("token file line {line}: {reason}")]
pub struct TokenFileError {
    /// 1-based line number.
    pub line: usize,
    /// What is wrong with it (never the token itself).
    pub reason: String,
}

fn digest(token: &[u8]) -> [u8; 32] {
    Sha256::digest(token).into()
}

impl TokenTable {
    /// Parses a token file (see the module docs); `#` starts a comment line, blank lines are
    /// skipped. A file without any token is refused: it would lock everyone out.
    pub fn parse(text: &str) -> Result<Self, TokenFileError> {
        let mut entries = Vec::new();
        for (i, raw) in text.lines().enumerate() {
            let line = i + 1;
            let err = |reason: String| TokenFileError { line, reason };
            let content = raw.trim();
            if content.is_empty() || content.starts_with('#') {
                continue;
            }
            let fields: Vec<&str> = content.split_whitespace().collect();
            if !(2..=3).contains(&fields.len()) {
                return Err(err(format!(
                    "expected `token role [experiment-ids|*]`, got {} fields",
                    fields.len()
                )));
            }
            let token = fields[0];
            if token.len() < MIN_TOKEN_LEN || !token.bytes().all(|b| b.is_ascii_graphic()) {
                return Err(err(format!(
                    "a token must be at least {MIN_TOKEN_LEN} visible ASCII characters"
                )));
            }
            let role = match fields[1] {
                "read" => Role::Read,
                "write" => Role::Write,
                "admin" => Role::Admin,
                other => {
                    return Err(err(format!(
                        "role {other:?} is not one of read, write, admin"
                    )));
                }
            };
            let scope = match fields.get(2) {
                None | Some(&"*") => Scope::All,
                Some(ids) => Scope::Only(
                    ids.split(',')
                        .map(|id| {
                            id.parse::<i64>().map_err(|_| {
                                err(format!(
                                    "experiment ids are comma-separated integers or `*`, got {id:?}"
                                ))
                            })
                        })
                        .collect::<Result<_, _>>()?,
                ),
            };
            let digest = digest(token.as_bytes());
            if entries.iter().any(|e: &Entry| e.digest == digest) {
                return Err(err("this token already appears on an earlier line".into()));
            }
            entries.push(Entry {
                digest,
                role,
                scope,
            });
        }
        if entries.is_empty() {
            return Err(TokenFileError {
                line: 0,
                reason: "the file holds no token".into(),
            });
        }
        Ok(Self { entries })
    }

    /// Number of tokens.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether there is no token.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The caller holding `token`, if it is known. Every entry is compared, in constant time,
    /// whatever matches.
    pub fn caller(&self, token: &[u8]) -> Option<Caller> {
        let d = digest(token);
        let mut found: Option<&Entry> = None;
        for e in &self.entries {
            if bool::from(e.digest.ct_eq(&d)) {
                found = Some(e);
            }
        }
        found.map(|e| Caller {
            role: e.role,
            scope: e.scope.clone(),
        })
    }
}

/// What a route needs: the role, and the experiment it touches (`None`: a server-wide route).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Requirement {
    /// The least role.
    pub role: Role,
    /// The experiment named by the path, if any; `Some(None)` when the path names one that is
    /// not an integer (the route answers 404 to anyone who may reach it).
    pub experiment: Option<Option<i64>>,
    /// Whether the route is the experiment listing, which its handler narrows to the caller's
    /// scope: the one server-wide route a scoped token reaches. Every other server-wide route
    /// (creating, `/metrics` with every experiment's totals) needs the scope `*`.
    pub listing: bool,
}

/// Routes open to anyone, tokens or not.
pub fn is_open(path: &str) -> bool {
    matches!(path, "/healthz" | "/readyz")
}

/// The requirement of a request for `method` on the route `template` (axum syntax) at `path`.
///
/// Reads (GET, HEAD), precondition queries and plans need `read`; creating experiments,
/// refits and exclusions (making and restoring) need `admin`; every other method needs
/// `write`. Routes under `/v1/experiments/{id}` touch experiment `id`.
pub fn requirement(method: &Method, template: &str, path: &str) -> Requirement {
    let role = if method == Method::GET || method == Method::HEAD {
        Role::Read
    } else if template == "/v1/experiments"
        || template.ends_with("/model/refit")
        || template.contains("/exclusions")
    {
        Role::Admin
    } else if template.ends_with("/precondition") || template.ends_with("/plans") {
        Role::Read
    } else {
        Role::Write
    };
    let experiment = template
        .starts_with("/v1/experiments/{id}")
        .then(|| path.split('/').nth(3).and_then(|id| id.parse().ok()));
    let listing = role == Role::Read && template == "/v1/experiments";
    Requirement {
        role,
        experiment,
        listing,
    }
}

/// Checks a caller against a requirement: `Ok` or the `403` to answer.
pub fn check(caller: &Caller, need: &Requirement) -> Result<(), ApiError> {
    if caller.role < need.role {
        return Err(ApiError::Forbidden(format!(
            "this route needs the {} role; the token has {}",
            need.role.as_str(),
            caller.role.as_str()
        )));
    }
    match (&need.experiment, &caller.scope) {
        (_, Scope::All) => Ok(()),
        (Some(Some(id)), scope) if scope.allows(*id) => Ok(()),
        (Some(Some(id)), _) => Err(ApiError::Forbidden(format!(
            "the token does not reach experiment {id}"
        ))),
        // Listing is narrowed by the handler; everything else server-wide needs `*`.
        (None, _) if need.listing => Ok(()),
        _ => Err(ApiError::Forbidden(
            "this route needs a token whose scope is `*`".into(),
        )),
    }
}

/// The bearer token of a request, if it sent one.
fn bearer(req: &Request) -> Option<&[u8]> {
    let value = req.headers().get(axum::http::header::AUTHORIZATION)?;
    let value = value.as_bytes();
    let (scheme, rest) = value.split_at(value.iter().position(|b| *b == b' ')?);
    if !scheme.eq_ignore_ascii_case(b"bearer") {
        return None;
    }
    let token = rest.trim_ascii();
    (!token.is_empty()).then_some(token)
}

/// The middleware: with a token table, every route but the open ones needs a token with the
/// route's role and experiment; the caller goes into the request's extensions.
pub async fn authorize(tokens: Option<Arc<TokenTable>>, mut req: Request, next: Next) -> Response {
    let Some(tokens) = tokens else {
        return next.run(req).await;
    };
    let path = req.uri().path().to_string();
    if is_open(&path) {
        return next.run(req).await;
    }
    let Some((caller, fingerprint)) =
        bearer(&req).and_then(|t| Some((tokens.caller(t)?, Fingerprint::of(t))))
    else {
        return ApiError::Unauthorized.into_response();
    };
    let template = req
        .extensions()
        .get::<MatchedPath>()
        .map_or(path.clone(), |m| m.as_str().to_string());
    if let Err(e) = check(&caller, &requirement(req.method(), &template, &path)) {
        return e.into_response();
    }
    req.extensions_mut().insert(caller);
    req.extensions_mut().insert(fingerprint);
    next.run(req).await
}

#[cfg(test)]
mod tests {
    use super::*;

    const FILE: &str = "\
# comment
aaaaaaaaaaaaaaaaaaaa read
bbbbbbbbbbbbbbbbbbbb write 3,4

cccccccccccccccccccc admin *
";

    #[test]
    fn a_token_file_parses_into_roles_and_scopes() {
        let t = TokenTable::parse(FILE).unwrap();
        assert_eq!(t.len(), 3);
        let read = t.caller(b"aaaaaaaaaaaaaaaaaaaa").unwrap();
        assert_eq!((read.role, read.scope), (Role::Read, Scope::All));
        let write = t.caller(b"bbbbbbbbbbbbbbbbbbbb").unwrap();
        assert_eq!(write.role, Role::Write);
        assert!(write.scope.allows(3) && write.scope.allows(4) && !write.scope.allows(5));
        assert_eq!(t.caller(b"cccccccccccccccccccc").unwrap().role, Role::Admin);
        assert_eq!(t.caller(b"aaaaaaaaaaaaaaaaaaab"), None);
        assert_eq!(t.caller(b""), None);
    }

    #[test]
    fn bad_lines_are_named_and_tokens_never_shown() {
        for (text, line) in [
            ("short read", 1),
            ("# x\naaaaaaaaaaaaaaaaaaaa owner", 2),
            ("aaaaaaaaaaaaaaaaaaaa read 1,x", 1),
            ("aaaaaaaaaaaaaaaaaaaa read * extra", 1),
            ("aaaaaaaaaaaaaaaaaaaa read\naaaaaaaaaaaaaaaaaaaa admin", 2),
            ("# nothing", 0),
        ] {
            let e = TokenTable::parse(text).unwrap_err();
            assert_eq!(e.line, line, "{text}: {e}");
            assert!(!e.to_string().contains("aaaaaaaa"), "{e}");
        }
        let debug = format!("{:?}", TokenTable::parse(FILE).unwrap());
        assert!(
            !debug.contains("aaaa") && debug.contains("Admin"),
            "{debug}"
        );
    }

    #[test]
    fn routes_need_the_documented_roles() {
        let need = |m: Method, t: &str, p: &str| requirement(&m, t, p);
        assert_eq!(
            need(
                Method::GET,
                "/v1/experiments/{id}/model",
                "/v1/experiments/7/model"
            ),
            Requirement {
                role: Role::Read,
                experiment: Some(Some(7)),
                listing: false,
            }
        );
        let r = need(
            Method::GET,
            "/v1/experiments/{id}/model/export",
            "/v1/experiments/7/model/export",
        );
        assert_eq!((r.role, r.experiment), (Role::Read, Some(Some(7))));
        let r = need(Method::POST, "/v1/experiments", "/v1/experiments");
        assert_eq!((r.role, r.experiment), (Role::Admin, None));
        let r = need(
            Method::POST,
            "/v1/experiments/{id}/model/refit",
            "/v1/experiments/2/model/refit",
        );
        assert_eq!(r.role, Role::Admin);
        for t in [
            "/v1/experiments/{id}/precondition",
            "/v1/experiments/{id}/plans",
        ] {
            assert_eq!(
                need(Method::POST, t, "/v1/experiments/1/x").role,
                Role::Read
            );
        }
        for t in [
            "/v1/experiments/{id}/trajectories",
            "/v1/experiments/{id}/proposals",
            "/v1/experiments/{id}/proposals/{pid}/abandon",
            "/v1/experiments/{id}/proposals/{pid}/continue",
        ] {
            assert_eq!(
                need(Method::POST, t, "/v1/experiments/1/x").role,
                Role::Write
            );
        }
    }

    #[test]
    fn scopes_and_roles_are_checked_together() {
        let scoped = Caller {
            role: Role::Write,
            scope: Scope::Only([3].into()),
        };
        let on = |id| Requirement {
            role: Role::Write,
            experiment: Some(Some(id)),
            listing: false,
        };
        assert!(check(&scoped, &on(3)).is_ok());
        assert!(check(&scoped, &on(4)).is_err());
        let list = requirement(&Method::GET, "/v1/experiments", "/v1/experiments");
        assert!(list.listing);
        assert!(check(&scoped, &list).is_ok());
        // Server-wide reads other than the listing (every experiment's totals) need `*`.
        let metrics = requirement(&Method::GET, "/metrics", "/metrics");
        assert!(!metrics.listing);
        assert!(check(&scoped, &metrics).is_err());
        let scoped_admin = Caller {
            role: Role::Admin,
            scope: Scope::Only([3].into()),
        };
        assert!(check(&scoped_admin, &metrics).is_err());
        let everything = Caller {
            role: Role::Read,
            scope: Scope::All,
        };
        assert!(check(&everything, &metrics).is_ok());
        let create = Requirement {
            role: Role::Admin,
            experiment: None,
            listing: false,
        };
        assert!(check(&scoped, &create).is_err());
        let admin = Caller {
            role: Role::Admin,
            scope: Scope::Only([3].into()),
        };
        assert!(check(&admin, &create).is_err(), "creating needs `*`");
        let reader = Caller {
            role: Role::Read,
            scope: Scope::All,
        };
        assert!(check(&reader, &on(3)).is_err());
    }
}
