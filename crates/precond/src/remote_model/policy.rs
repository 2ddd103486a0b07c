//! Where remote models may live: the operator's URL prefixes, and the one reading of a model
//! URL that both the check and the HTTP client use.
//!
//! A URL is checked and called in the same form: [`ModelUrlPolicy::normalise`] parses it as
//! the WHATWG URL standard does (the `url` crate: `HTTP://Host:80/a/./b` becomes
//! `http://host/a/b`), refuses what two parsers could read differently (whitespace and control
//! characters, which one strips and another sends; backslashes, a `/` to one and part of a name
//! to another; percent-encoded `/`, `\` and `.` in the path, which model servers decode or not
//! before routing; credentials; fragments; more than
//! [`MAX_URL_LEN`] characters), checks that the HTTP client reads the normalised form to the
//! same host, port and path, checks that against the allowed prefixes, and returns it. The
//! experiment stores that normalised form, and every call re-checks it against the prefixes
//! allowed *now*, so a prefix the operator removes stops its models at once.

use reqwest::Url;

/// Longest accepted model URL, in bytes.
pub const MAX_URL_LEN: usize = 2048;

/// Where remote models may live: URL prefixes the operator allows (`--allow-model-url`).
///
/// A URL is allowed when it has the scheme, host and port of an allowed prefix and its
/// (normalised) path starts with the prefix's path. Nothing is allowed by default.
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
        self.normalise(url).map(drop)
    }

    /// The form of `url` that is checked, stored and called, if it may be called; the error
    /// says why not (see the module docs).
    pub fn normalise(&self, url: &str) -> Result<String, String> {
        if url.len() > MAX_URL_LEN {
            return Err(format!("longer than {MAX_URL_LEN} characters"));
        }
        if let Some(c) = url.chars().find(|c| c.is_whitespace() || c.is_control()) {
            return Err(format!(
                "must not contain whitespace or control characters (found U+{:04X})",
                c as u32
            ));
        }
        if url.contains('\\') {
            return Err(
                "must not contain a backslash: the URL standard reads it as `/`, other parsers \
                 as part of a name"
                    .into(),
            );
        }
        let parsed = Url::parse(url).map_err(|e| format!("not a valid URL: {e}"))?;
        if parsed.scheme() != "http" {
            return Err("only http:// model URLs are supported".into());
        }
        if !parsed.username().is_empty() || parsed.password().is_some() {
            return Err("a model URL may not carry credentials".into());
        }
        if parsed.fragment().is_some() {
            return Err("a model URL has no fragment (`#…`)".into());
        }
        let path = parsed.path().to_ascii_lowercase();
        if ["%2f", "%5c", "%2e"].iter().any(|e| path.contains(e)) {
            return Err(
                "the path may not percent-encode `/`, `\\` or `.`: model servers decode them \
                 differently before routing"
                    .into(),
            );
        }
        let normalised = parsed.as_str().to_string();
        same_for_the_client(&parsed, &normalised)?;
        let allowed = self.prefixes.iter().any(|p| {
            p.scheme() == parsed.scheme()
                && p.host_str() == parsed.host_str()
                && p.port_or_known_default() == parsed.port_or_known_default()
                && parsed.path().starts_with(p.path())
        });
        if allowed {
            Ok(normalised)
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

/// Checks that the HTTP client (`ureq`, which parses with the `http` crate) reads `normalised`
/// to the host, port, path and query `parsed` has.
fn same_for_the_client(parsed: &Url, normalised: &str) -> Result<(), String> {
    let differs = || Err("the HTTP client would read this URL differently".to_string());
    let Ok(uri) = ureq::http::Uri::try_from(normalised) else {
        return differs();
    };
    let host = parsed
        .host_str()
        .map(|h| h.trim_start_matches('[').trim_end_matches(']'));
    let client_host = uri
        .host()
        .map(|h| h.trim_start_matches('[').trim_end_matches(']'));
    let query = parsed.query().map(|q| format!("?{q}")).unwrap_or_default();
    let path_and_query = format!("{}{query}", parsed.path());
    if uri.scheme_str() != Some("http")
        || client_host.map(str::to_ascii_lowercase) != host.map(str::to_ascii_lowercase)
        || uri.port_u16().unwrap_or(80) != parsed.port_or_known_default().unwrap_or(80)
        || uri.path_and_query().map(|p| p.as_str()) != Some(path_and_query.as_str())
    {
        return differs();
    }
    Ok(())
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
    fn what_is_stored_and_called_is_the_normalised_form_the_check_saw() {
        let p = ModelUrlPolicy::new(&["http://127.0.0.1:9000/ok/"]).unwrap();
        for (given, stored) in [
            (
                "http://127.0.0.1:9000/ok/predict",
                "http://127.0.0.1:9000/ok/predict",
            ),
            (
                "HTTP://127.0.0.1:9000/ok/./predict",
                "http://127.0.0.1:9000/ok/predict",
            ),
            (
                "http://127.0.0.1.:9000/ok/predict",
                "http://127.0.0.1:9000/ok/predict",
            ),
            (
                "http://127\u{3002}0\u{3002}0\u{3002}1:9000/ok/predict",
                "http://127.0.0.1:9000/ok/predict",
            ),
            (
                "http://127.0.0.1:09000/ok/predict?arm=2",
                "http://127.0.0.1:9000/ok/predict?arm=2",
            ),
        ] {
            assert_eq!(p.normalise(given).as_deref(), Ok(stored), "{given:?}");
        }
    }

    #[test]
    fn urls_two_parsers_could_read_differently_are_refused() {
        let p = ModelUrlPolicy::new(&["http://127.0.0.1:9000/"]).unwrap();
        let long = format!("http://127.0.0.1:9000/{}", "a".repeat(MAX_URL_LEN));
        for (url, why) in [
            ("http://127.0.0.1:9000/o\tk/predict", "control"),
            (
                "http://127.0.0.1:9000/ok/predict\r\nX-Injected: 1",
                "control",
            ),
            ("http://127.0.0.1:9000/ok/pre dict", "whitespace"),
            ("  http://127.0.0.1:9000/ok/predict", "whitespace"),
            (
                "http://127.0.0.1:9000/ok/predict\u{0}@127.0.0.1:1/",
                "control",
            ),
            ("http://127.0.0.1:9000/ok/..%2fadmin", "percent-encode"),
            ("http://127.0.0.1:9000/ok%2F..%2Fadmin", "percent-encode"),
            ("http://127.0.0.1:9000/ok/predict#@evil", "fragment"),
            (
                "http://127.0.0.1:9000@127.0.0.1:1/ok/predict",
                "credentials",
            ),
            (long.as_str(), "longer"),
        ] {
            let e = p.normalise(url).unwrap_err();
            assert!(e.contains(why), "{url:?}: {e}");
        }
        // A backslash is a slash to the URL standard, part of the user name to others.
        for url in [
            "http://127.0.0.1:9000\\@127.0.0.1:1/ok/predict",
            "http://127.0.0.1:9000/ok\\..\\admin",
        ] {
            assert!(p.normalise(url).unwrap_err().contains("backslash"), "{url}");
        }
        // Dot segments are resolved before the prefix is compared.
        let ok = ModelUrlPolicy::new(&["http://127.0.0.1:9000/ok/"]).unwrap();
        for url in [
            "http://127.0.0.1:9000/ok/../admin",
            "http://127.0.0.1:9000/ok/%2e%2e/admin",
        ] {
            assert!(
                ok.normalise(url).unwrap_err().contains("not under"),
                "{url}"
            );
        }
    }
}
