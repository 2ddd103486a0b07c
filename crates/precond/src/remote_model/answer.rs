//! A model's answer, parsed from the response stream within what was asked: at most one row
//! per point sent, each of exactly the state's dimension, finite; at most one validity flag per
//! point. The parse stops at the first row too many or too wide, so what a hostile model can
//! make the server hold is `points × dimension` numbers, whatever it sends (a 64 MiB body of
//! `[[0],[0],…]` once cost 1.2 GB of parsed vectors).

use serde::de::{DeserializeSeed, Error as _, IgnoredAny, MapAccess, SeqAccess, Visitor};
use std::fmt;
use std::io::Read as _;

/// What a model answered for `n` points, checked.
#[derive(Debug, Clone, PartialEq)]
pub struct Answer {
    /// One next state per point.
    pub next_states: Vec<Vec<f64>>,
    /// One validity flag per point, when the model sent them.
    pub valid: Option<Vec<bool>>,
}

/// Parses `{"next_states": [[...] × n], "valid"?: [bool × n] | null}` (other fields ignored)
/// for `n` points of dimension `dim`.
#[derive(Debug, Clone, Copy)]
pub struct AnswerSeed {
    /// Points sent.
    pub n: usize,
    /// The state's dimension.
    pub dim: usize,
}

impl<'de> DeserializeSeed<'de> for AnswerSeed {
    type Value = Answer;

    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<Answer, D::Error> {
        d.deserialize_map(self)
    }
}

impl<'de> Visitor<'de> for AnswerSeed {
    type Value = Answer;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str(r#"{"next_states": [[...]], "valid"?: [...]}"#)
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Answer, A::Error> {
        let mut next_states = None;
        let mut valid = None;
        while let Some(key) = map.next_key::<std::borrow::Cow<'de, str>>()? {
            match key.as_ref() {
                "next_states" if next_states.is_some() => {
                    return Err(A::Error::custom("`next_states` appears twice"));
                }
                "next_states" => next_states = Some(map.next_value_seed(Rows(self))?),
                "valid" if valid.is_some() => {
                    return Err(A::Error::custom("`valid` appears twice"));
                }
                "valid" => valid = Some(map.next_value_seed(OptionalFlags(self.n))?),
                _ => {
                    map.next_value::<IgnoredAny>()?;
                }
            }
        }
        let next_states = next_states.ok_or_else(|| A::Error::missing_field("next_states"))?;
        Ok(Answer {
            next_states,
            valid: valid.flatten(),
        })
    }
}

/// The rows: exactly `n`, refused at the `n + 1`-th.
struct Rows(AnswerSeed);

impl<'de> DeserializeSeed<'de> for Rows {
    type Value = Vec<Vec<f64>>;

    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
        d.deserialize_seq(self)
    }
}

impl<'de> Visitor<'de> for Rows {
    type Value = Vec<Vec<f64>>;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        write!(f, "{} next states", self.0.n)
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
        let AnswerSeed { n, dim } = self.0;
        let mut rows = Vec::with_capacity(n);
        while let Some(row) = seq.next_element_seed(Row {
            dim,
            index: rows.len(),
        })? {
            if rows.len() == n {
                return Err(A::Error::custom(format!(
                    "answered more than {n} next states for {n} points"
                )));
            }
            rows.push(row);
        }
        if rows.len() != n {
            return Err(A::Error::custom(format!(
                "answered {} next states for {n} points",
                rows.len()
            )));
        }
        Ok(rows)
    }
}

/// One row: exactly `dim` finite numbers, refused at the `dim + 1`-th.
struct Row {
    dim: usize,
    index: usize,
}

impl<'de> DeserializeSeed<'de> for Row {
    type Value = Vec<f64>;

    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
        d.deserialize_seq(self)
    }
}

impl<'de> Visitor<'de> for Row {
    type Value = Vec<f64>;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        write!(f, "a next state of {} numbers", self.dim)
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
        let (dim, i) = (self.dim, self.index);
        let mut row = Vec::with_capacity(dim);
        while let Some(x) = seq.next_element::<f64>()? {
            if row.len() == dim {
                return Err(A::Error::custom(format!(
                    "next_states[{i}] has more than {dim} components, the state has {dim}"
                )));
            }
            if !x.is_finite() {
                return Err(A::Error::custom(format!("next_states[{i}] is not finite")));
            }
            row.push(x);
        }
        if row.len() != dim {
            return Err(A::Error::custom(format!(
                "next_states[{i}] has {} components, the state has {dim}",
                row.len()
            )));
        }
        Ok(row)
    }
}

/// `null` or exactly `n` flags, refused at the `n + 1`-th.
struct OptionalFlags(usize);

impl<'de> DeserializeSeed<'de> for OptionalFlags {
    type Value = Option<Vec<bool>>;

    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
        d.deserialize_option(self)
    }
}

impl<'de> Visitor<'de> for OptionalFlags {
    type Value = Option<Vec<bool>>;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        write!(f, "null or {} validity flags", self.0)
    }

    fn visit_none<E: serde::de::Error>(self) -> Result<Self::Value, E> {
        Ok(None)
    }

    fn visit_unit<E: serde::de::Error>(self) -> Result<Self::Value, E> {
        Ok(None)
    }

    fn visit_some<D: serde::Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
        d.deserialize_seq(self)
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
        let n = self.0;
        let mut flags = Vec::with_capacity(n);
        while let Some(flag) = seq.next_element::<bool>()? {
            if flags.len() == n {
                return Err(A::Error::custom(format!(
                    "answered more than {n} validity flags for {n} points"
                )));
            }
            flags.push(flag);
        }
        if flags.len() != n {
            return Err(A::Error::custom(format!(
                "answered {} validity flags for {n} points",
                flags.len()
            )));
        }
        Ok(Some(flags))
    }
}

/// Parses a whole answer from `reader` (trailing whitespace allowed, nothing else).
pub fn parse(reader: impl std::io::Read, seed: AnswerSeed) -> Result<Answer, serde_json::Error> {
    let mut de = serde_json::Deserializer::from_reader(reader);
    let answer = seed.deserialize(&mut de)?;
    de.end()?;
    Ok(answer)
}

/// Why a binary answer was refused.
#[derive(Debug)]
pub enum BinaryError {
    /// The stream failed (a timeout, a body past the limit).
    Read(std::io::Error),
    /// The bytes are not `n × dim` finite little-endian `f64`s, optionally followed by `n`
    /// flags of 0 or 1.
    Shape(String),
}

/// Parses a binary answer ([`F64LE_CONTENT_TYPE`](super::F64LE_CONTENT_TYPE)) for `n` points
/// of dimension `dim`: `n × dim` little-endian `f64`s, row-major, finite, optionally followed
/// by one byte (0 or 1) of validity per point. Reads at most one byte past the longest
/// well-formed answer, so a model cannot make the server hold more than that.
pub fn parse_f64le(
    reader: impl std::io::Read,
    n: usize,
    dim: usize,
) -> Result<Answer, BinaryError> {
    let numbers = n * dim;
    let (short, long) = (8 * numbers, 8 * numbers + n);
    let mut body = Vec::with_capacity(long);
    reader
        .take(long as u64 + 1)
        .read_to_end(&mut body)
        .map_err(BinaryError::Read)?;
    if body.len() != short && body.len() != long {
        return Err(BinaryError::Shape(format!(
            "answered {}{} bytes of f64le; {n} next states of {dim} numbers are {short} bytes \
             ({long} with a validity byte per point)",
            body.len().min(long),
            if body.len() > long { "+" } else { "" },
        )));
    }
    let values: Vec<f64> = body[..short]
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().expect("8 bytes")))
        .collect();
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(BinaryError::Shape(format!(
            "answered a non-finite number at point {}, component {}",
            i / dim.max(1),
            i % dim.max(1)
        )));
    }
    let valid = if body.len() == long {
        let flags = &body[short..];
        if let Some(i) = flags.iter().position(|&f| f > 1) {
            return Err(BinaryError::Shape(format!(
                "answered validity byte {} at point {i}; flags are 0 or 1",
                flags[i]
            )));
        }
        Some(flags.iter().map(|&f| f == 1).collect())
    } else {
        None
    };
    let next_states = if dim == 0 {
        vec![Vec::new(); n]
    } else {
        values.chunks_exact(dim).map(<[f64]>::to_vec).collect()
    };
    Ok(Answer { next_states, valid })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Read;

    fn f64le(values: &[f64], flags: &[u8]) -> Vec<u8> {
        let mut out: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        out.extend_from_slice(flags);
        out
    }

    #[test]
    fn a_binary_answer_parses_with_or_without_flags_and_is_checked() {
        let a = parse_f64le(&f64le(&[0.5, 1.0, 2.0, 3e-3], &[])[..], 2, 2).unwrap();
        assert_eq!(a.next_states, vec![vec![0.5, 1.0], vec![2.0, 3e-3]]);
        assert_eq!(a.valid, None);
        let a = parse_f64le(&f64le(&[0.5, 1.0, 2.0, 3e-3], &[1, 0])[..], 2, 2).unwrap();
        assert_eq!(a.valid, Some(vec![true, false]));
        let shape = |r: Result<Answer, BinaryError>| match r {
            Err(BinaryError::Shape(reason)) => reason,
            other => panic!("{other:?}"),
        };
        // One number short, one byte too many, a flag of 2, a NaN.
        let r = shape(parse_f64le(&f64le(&[0.5, 1.0, 2.0], &[])[..], 2, 2));
        assert!(
            r.contains("answered 24 bytes") && r.contains("32 bytes"),
            "{r}"
        );
        let r = shape(parse_f64le(
            &f64le(&[0.5, 1.0, 2.0, 3.0], &[1, 1, 1])[..],
            2,
            2,
        ));
        assert!(r.contains("answered 34+ bytes"), "{r}");
        let r = shape(parse_f64le(
            &f64le(&[0.5, 1.0, 2.0, 3.0], &[1, 2])[..],
            2,
            2,
        ));
        assert!(r.contains("validity byte 2 at point 1"), "{r}");
        let r = shape(parse_f64le(
            &f64le(&[0.5, 1.0, f64::NAN, 3.0], &[])[..],
            2,
            2,
        ));
        assert!(r.contains("point 1, component 0"), "{r}");
    }

    fn seed(n: usize, dim: usize) -> AnswerSeed {
        AnswerSeed { n, dim }
    }

    #[test]
    fn a_well_formed_answer_parses_with_or_without_flags() {
        let a = parse(
            &br#"{"next_states": [[0.5, 1], [2, 3e-3]], "extra": {"x": [1, 2]}}"#[..],
            seed(2, 2),
        )
        .unwrap();
        assert_eq!(a.next_states, vec![vec![0.5, 1.0], vec![2.0, 3e-3]]);
        assert_eq!(a.valid, None);
        let a = parse(
            &br#"{"valid": [true, false], "next_states": [[1], [2]]}"#[..],
            seed(2, 1),
        )
        .unwrap();
        assert_eq!(a.valid, Some(vec![true, false]));
        let a = parse(&br#"{"next_states": [[1]], "valid": null}"#[..], seed(1, 1)).unwrap();
        assert_eq!(a.valid, None);
    }

    #[test]
    fn every_wrong_shape_is_named() {
        for (body, n, dim, why) in [
            (
                r#"{"next_states": [[1], [2]]}"#,
                1,
                1,
                "more than 1 next states",
            ),
            (
                r#"{"next_states": [[1]]}"#,
                2,
                1,
                "answered 1 next states for 2",
            ),
            (
                r#"{"next_states": [[1, 2, 3]]}"#,
                1,
                2,
                "more than 2 components",
            ),
            (r#"{"next_states": [[]]}"#, 1, 2, "has 0 components"),
            (r#"{"next_states": [[1e999]]}"#, 1, 1, ""),
            (r#"{"next_states": [[NaN]]}"#, 1, 1, ""),
            (
                r#"{"next_states": [[1]], "valid": [true, true]}"#,
                1,
                1,
                "more than 1 validity",
            ),
            (r#"{"valid": [true]}"#, 1, 1, "next_states"),
            (
                r#"{"next_states": [[1]], "next_states": [[1]]}"#,
                1,
                1,
                "twice",
            ),
            (r#"{"next_states": [[1]]} trailing"#, 1, 1, "trailing"),
            (r#"[[1]]"#, 1, 1, ""),
        ] {
            let e = parse(body.as_bytes(), seed(n, dim))
                .unwrap_err()
                .to_string();
            assert!(e.contains(why), "{body}: {e}");
        }
    }

    /// A reader that fails the test if more than `limit` bytes are read from it.
    struct Tripwire<'a> {
        data: &'a [u8],
        limit: usize,
        read: usize,
    }

    impl Read for Tripwire<'_> {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            let n = buf.len().min(self.data.len() - self.read).min(1);
            buf[..n].copy_from_slice(&self.data[self.read..self.read + n]);
            self.read += n;
            assert!(
                self.read <= self.limit,
                "read {} bytes, past the row that was one too many",
                self.read
            );
            Ok(n)
        }
    }

    /// Bytes serde_json may read past a refused value while it unwinds (it still checks the
    /// enclosing `]` and `}`).
    const SLACK: usize = 16;

    #[test]
    fn the_parse_stops_at_the_first_row_too_many_or_too_wide() {
        // 3 points asked; a fourth row, then a million more: the parse must stop inside the
        // fourth, whatever follows.
        let mut body = br#"{"next_states": [[0], [0], [0], [0]"#.to_vec();
        let stop = body.len();
        body.extend(std::iter::repeat_n(&b", [0]"[..], 1_000_000).flatten());
        body.extend(b"]}");
        let e = parse(
            Tripwire {
                data: &body,
                limit: stop + SLACK,
                read: 0,
            },
            seed(3, 1),
        )
        .unwrap_err();
        assert!(e.to_string().contains("more than 3 next states"), "{e}");
        // A row of a million components stops at the third.
        let mut body = br#"{"next_states": [[0, 0, 0"#.to_vec();
        let stop = body.len();
        body.extend(std::iter::repeat_n(&b", 0"[..], 1_000_000).flatten());
        body.extend(b"]]}");
        let e = parse(
            Tripwire {
                data: &body,
                limit: stop + SLACK,
                read: 0,
            },
            seed(1, 2),
        )
        .unwrap_err();
        assert!(e.to_string().contains("more than 2 components"), "{e}");
    }
}
