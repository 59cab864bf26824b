//! A parser for the subset of Python literals that mrcal `.cameramodel` files use (what
//! `ast.literal_eval` accepts, minus sets and complex numbers): dicts, lists, tuples, strings and
//! byte strings (with implicit concatenation), ints, floats, `True`, `False`, `None`, `#` comments.

use gelstereo_core::limits::{ECHO_CHARS, shorten};

/// A parsed Python literal.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Value {
    /// `None`.
    None,
    /// `True` / `False`.
    Bool(bool),
    /// An integer literal (kept as f64 too; `is_int` says it was written without a point).
    Int(i64),
    /// A float literal.
    Float(f64),
    /// A str literal.
    Str(String),
    /// A bytes literal (content not decoded; mrcal's `optimization_inputs`).
    Bytes(usize),
    /// A list or a tuple.
    List(Vec<Value>),
    /// A dict with string keys, in file order.
    Dict(Vec<(String, Value)>),
}

impl Value {
    /// A short description of the type and shape, for error messages.
    pub(crate) fn describe(&self) -> String {
        match self {
            Value::None => "None".to_owned(),
            Value::Bool(b) => format!("the bool {}", if *b { "True" } else { "False" }),
            Value::Int(i) => format!("the integer {i}"),
            Value::Float(f) => format!("the number {f}"),
            Value::Str(s) => format!("the string '{}'", shorten(s, ECHO_CHARS)),
            Value::Bytes(n) => format!("a byte string of {n} bytes"),
            Value::List(items) => {
                if items.iter().all(|v| v.as_f64().is_some()) {
                    format!("a list of {} numbers", items.len())
                } else {
                    format!("a list of {} items, not all numbers", items.len())
                }
            }
            Value::Dict(d) => format!("a dict of {} keys", d.len()),
        }
    }

    /// The number, for ints and floats.
    pub(crate) fn as_f64(&self) -> Option<f64> {
        match self {
            // mrcal's integers (image sizes, 0 in extrinsics) are small; exact in f64.
            #[allow(clippy::cast_precision_loss)]
            Value::Int(i) => Some(*i as f64),
            Value::Float(f) => Some(*f),
            _ => None,
        }
    }
}

/// A parse failure: 1-based line and message.
#[derive(Debug)]
pub(crate) struct ParseError {
    pub line: usize,
    pub message: String,
}

struct Parser<'a> {
    s: &'a [u8],
    pos: usize,
    depth: usize,
}

/// Parses one Python literal (the whole text; trailing garbage is an error).
pub(crate) fn parse(text: &str) -> Result<Value, ParseError> {
    let mut p = Parser {
        s: text.as_bytes(),
        pos: 0,
        depth: 0,
    };
    let v = p.value()?;
    p.skip_ws();
    if p.pos < p.s.len() {
        return Err(p.err("unexpected text after the literal"));
    }
    Ok(v)
}

impl Parser<'_> {
    fn line(&self) -> usize {
        1 + self.s[..self.pos.min(self.s.len())]
            .iter()
            .filter(|&&c| c == b'\n')
            .count()
    }

    fn err(&self, message: &str) -> ParseError {
        let found = match self.s.get(self.pos) {
            Some(c) => format!(" (found '{}')", char::from(*c)),
            None => " (found end of file)".to_owned(),
        };
        ParseError {
            line: self.line(),
            message: format!("{message}{found}"),
        }
    }

    fn skip_ws(&mut self) {
        while let Some(&c) = self.s.get(self.pos) {
            if c == b'#' {
                while self.s.get(self.pos).is_some_and(|&c| c != b'\n') {
                    self.pos += 1;
                }
            } else if c.is_ascii_whitespace() || (c == b'\\' && self.s.get(self.pos + 1) == Some(&b'\n')) {
                self.pos += 1;
            } else {
                break;
            }
        }
    }

    fn peek(&mut self) -> Option<u8> {
        self.skip_ws();
        self.s.get(self.pos).copied()
    }

    fn value(&mut self) -> Result<Value, ParseError> {
        self.depth += 1;
        if self.depth > 64 {
            return Err(self.err("nesting deeper than 64"));
        }
        let v = match self.peek() {
            Some(b'{') => self.dict(),
            Some(b'[') => self.seq(b']'),
            Some(b'(') => self.seq(b')'),
            Some(b'\'' | b'"') => self.strings(false),
            Some(b'b' | b'B') if matches!(self.s.get(self.pos + 1), Some(b'\'' | b'"')) => {
                self.pos += 1;
                self.strings(true)
            }
            Some(c) if c == b'-' || c == b'+' || c == b'.' || c.is_ascii_digit() => self.number(),
            Some(c) if c.is_ascii_alphabetic() => self.word(),
            _ => Err(self.err("expected a value")),
        };
        self.depth -= 1;
        v
    }

    fn dict(&mut self) -> Result<Value, ParseError> {
        self.pos += 1;
        let mut out: Vec<(String, Value)> = Vec::new();
        loop {
            if self.peek() == Some(b'}') {
                self.pos += 1;
                return Ok(Value::Dict(out));
            }
            let key = match self.value()? {
                Value::Str(s) => s,
                other => {
                    return Err(ParseError {
                        line: self.line(),
                        message: format!("dict key must be a string, found {}", other.describe()),
                    });
                }
            };
            if self.peek() != Some(b':') {
                return Err(self.err("expected ':' after a dict key"));
            }
            self.pos += 1;
            let v = self.value()?;
            // Python keeps the last of duplicate keys.
            out.retain(|(k, _)| *k != key);
            out.push((key, v));
            match self.peek() {
                Some(b',') => self.pos += 1,
                Some(b'}') => {}
                _ => return Err(self.err("expected ',' or '}' in a dict")),
            }
        }
    }

    fn seq(&mut self, close: u8) -> Result<Value, ParseError> {
        self.pos += 1;
        let mut out = Vec::new();
        loop {
            if self.peek() == Some(close) {
                self.pos += 1;
                return Ok(Value::List(out));
            }
            out.push(self.value()?);
            match self.peek() {
                Some(b',') => self.pos += 1,
                Some(c) if c == close => {}
                _ => return Err(self.err("expected ',' or the end of a list")),
            }
        }
    }

    /// One or more adjacent string literals (Python concatenates them).
    fn strings(&mut self, bytes: bool) -> Result<Value, ParseError> {
        let mut text = String::new();
        let mut nbytes = 0;
        while let Some(&q) = self.s.get(self.pos) {
            if q != b'\'' && q != b'"' {
                break;
            }
            let triple = self.s.get(self.pos..self.pos + 3) == Some(&[q, q, q][..]);
            self.pos += if triple { 3 } else { 1 };
            let mut buf = Vec::new();
            loop {
                let Some(&c) = self.s.get(self.pos) else {
                    return Err(self.err("unterminated string"));
                };
                if c == q && (!triple || self.s.get(self.pos..self.pos + 3) == Some(&[q, q, q][..])) {
                    self.pos += if triple { 3 } else { 1 };
                    break;
                }
                if c == b'\n' && !triple {
                    return Err(self.err("newline inside a string"));
                }
                if c == b'\\' {
                    self.pos += 1;
                    let Some(&e) = self.s.get(self.pos) else {
                        return Err(self.err("unterminated string"));
                    };
                    match e {
                        b'n' => buf.push(b'\n'),
                        b't' => buf.push(b'\t'),
                        b'\\' | b'\'' | b'"' => buf.push(e),
                        b'\n' => {}
                        _ => {
                            buf.push(b'\\');
                            buf.push(e);
                        }
                    }
                } else {
                    buf.push(c);
                }
                self.pos += 1;
            }
            nbytes += buf.len();
            text.push_str(&String::from_utf8_lossy(&buf));
            // Implicit concatenation: another literal of the same kind may follow.
            self.skip_ws();
            if bytes
                && matches!(self.s.get(self.pos), Some(b'b' | b'B'))
                && matches!(self.s.get(self.pos + 1), Some(b'\'' | b'"'))
            {
                self.pos += 1;
            }
        }
        Ok(if bytes {
            Value::Bytes(nbytes)
        } else {
            Value::Str(text)
        })
    }

    fn number(&mut self) -> Result<Value, ParseError> {
        let start = self.pos;
        while self
            .s
            .get(self.pos)
            .is_some_and(|&c| c.is_ascii_alphanumeric() || matches!(c, b'.' | b'+' | b'-' | b'_'))
        {
            // A sign is only part of a number at the start or right after an exponent marker.
            let c = self.s[self.pos];
            if (c == b'+' || c == b'-') && self.pos > start && !matches!(self.s[self.pos - 1], b'e' | b'E') {
                break;
            }
            self.pos += 1;
        }
        let text: String = String::from_utf8_lossy(&self.s[start..self.pos]).replace('_', "");
        if let Ok(i) = text.parse::<i64>() {
            return Ok(Value::Int(i));
        }
        let is_float_syntax = text
            .trim_start_matches(['+', '-'])
            .chars()
            .next()
            .is_some_and(|c| c.is_ascii_digit() || c == '.')
            && text
                .chars()
                .all(|c| c.is_ascii_digit() || matches!(c, '.' | 'e' | 'E' | '+' | '-'));
        match text.parse::<f64>() {
            Ok(f) if is_float_syntax && f.is_finite() => Ok(Value::Float(f)),
            _ => {
                self.pos = start;
                Err(self.err(&format!("'{}' is not a number", shorten(&text, ECHO_CHARS))))
            }
        }
    }

    fn word(&mut self) -> Result<Value, ParseError> {
        let start = self.pos;
        while self
            .s
            .get(self.pos)
            .is_some_and(|&c| c.is_ascii_alphanumeric() || c == b'_')
        {
            self.pos += 1;
        }
        match &self.s[start..self.pos] {
            b"None" => Ok(Value::None),
            b"True" => Ok(Value::Bool(true)),
            b"False" => Ok(Value::Bool(false)),
            w => {
                let w = String::from_utf8_lossy(w).into_owned();
                self.pos = start;
                Err(self.err(&format!("'{}' is not a Python literal", shorten(&w, ECHO_CHARS))))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_mrcal_like_text() {
        let v = parse(
            "# note\n{\n 'lensmodel':  'LENSMODEL_OPENCV8',\n 'intrinsics': [ 600, 605.5, -1e-3, .5,],\n \
             'x': (1, 2), 'b': b'ab' b\"cd\", 's': 'a' \"b\", 'n': None, 't': True,\n}\n",
        )
        .unwrap();
        let Value::Dict(d) = v else { panic!() };
        assert_eq!(d[0], ("lensmodel".into(), Value::Str("LENSMODEL_OPENCV8".into())));
        assert_eq!(
            d[1].1,
            Value::List(vec![
                Value::Int(600),
                Value::Float(605.5),
                Value::Float(-1e-3),
                Value::Float(0.5)
            ])
        );
        assert_eq!(d[2].1, Value::List(vec![Value::Int(1), Value::Int(2)]));
        assert_eq!(d[3].1, Value::Bytes(4));
        assert_eq!(d[4].1, Value::Str("ab".into()));
        assert_eq!(d[5].1, Value::None);
        assert_eq!(d[6].1, Value::Bool(true));
    }

    /// Random texts over the literal alphabet, and random edits of a real model: parse returns
    /// Ok or Err, never panics; deep nesting is refused.
    #[test]
    fn never_panics_on_random_text() {
        let alphabet: &[u8] = b"{}[](),:'\"#\\\n -+.eE0123456789abNTFrx_";
        let model =
            "{ 'lensmodel': 'LENSMODEL_OPENCV4', 'intrinsics': [ 1, 2.5, -3e-2, 4,],\n 'b': b'x' b'y',}";
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for i in 0..20_000 {
            let text: Vec<u8> = if i % 2 == 0 {
                let n = (next() % 40) as usize;
                (0..n)
                    .map(|_| alphabet[(next() % alphabet.len() as u64) as usize])
                    .collect()
            } else {
                let mut t = model.as_bytes().to_vec();
                for _ in 0..1 + next() % 3 {
                    let at = (next() % t.len() as u64) as usize;
                    t[at] = alphabet[(next() % alphabet.len() as u64) as usize];
                }
                t
            };
            let _ = parse(&String::from_utf8_lossy(&text));
        }
        let deep = format!("{}1{}", "[".repeat(100), "]".repeat(100));
        assert!(parse(&deep).unwrap_err().message.contains("nesting"));
    }

    #[test]
    fn rejects_bad_text_with_line() {
        for (text, line) in [
            ("{\n'a': [1, 2,\n", 3),
            ("{'a': nan}", 1),
            ("{'a': 1}\n{}", 2),
            ("{1: 2}", 1),
            ("{'a' 1}", 1),
            ("[1 2]", 1),
            ("'abc", 1),
            ("{'a': 1e400}", 1),
        ] {
            let e = parse(text).unwrap_err();
            assert_eq!(e.line, line, "{text:?}: {}", e.message);
        }
    }
}
