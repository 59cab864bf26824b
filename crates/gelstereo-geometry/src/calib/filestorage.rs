//! The part of OpenCV's FileStorage format a calibration uses, read in Rust: YAML (as OpenCV writes
//! it, `%YAML:1.0` first line, and plain YAML 1.2) and XML (`<opencv_storage>`).
//!
//! OpenCV's own FileStorage parser is not used for reading: on some malformed files (a byte changed,
//! inserted or cut) it reads out of bounds and the process dies with SIGSEGV, which no error handling
//! can catch. The parsers here (`yaml-rust2`, `roxmltree`) are safe Rust; the nesting depth is bounded
//! before they run ([`super::structure`]), so their recursion and ours stay shallow.
//!
//! What is understood is what `cv::FileNode` would give a calibration reader: numbers, strings,
//! sequences, maps, and matrices (`rows`, `cols`, `dt`, `data`, with or without the `!!opencv-matrix`
//! tag / `type_id` attribute). In XML, an element's text of several numbers is a sequence, `<_>`
//! children are sequence items, other children are map entries.

use std::path::Path;

use gelstereo_core::limits::{ECHO_CHARS, shorten};
use roxmltree::{Document, ParsingOptions};
use yaml_rust2::parser::{Event, MarkedEventReceiver, Parser};
use yaml_rust2::scanner::{Marker, ScanError};
use yaml_rust2::{Yaml, YamlLoader};

use super::structure::syntax;
use crate::error::Result;

/// Most XML nodes a calibration file may hold (a 12-coefficient stereo calibration has ~60).
const MAX_XML_NODES: u32 = 100_000;

/// A value of a FileStorage file.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Value {
    /// A number (OpenCV does not tell integers from reals once read as `double`).
    Number(f64),
    /// A string, or a scalar that is not a number.
    Text(String),
    /// An empty value (`K1:` with nothing, `<K1/>`).
    Empty,
    /// A sequence.
    Seq(Vec<Value>),
    /// A map, entries in file order.
    Map(Vec<(String, Value)>),
}

impl Value {
    /// The entry `key` of a map (the first, as OpenCV takes it).
    pub(crate) fn get(&self, key: &str) -> Option<&Value> {
        match self {
            Value::Map(entries) => entries.iter().find(|(k, _)| k == key).map(|(_, v)| v),
            _ => None,
        }
    }

    /// Words for what this value is, for errors.
    pub(crate) fn describe(&self) -> String {
        match self {
            Value::Number(v) => format!("the number {v}"),
            Value::Text(s) => format!("the string '{}'", shorten(s, ECHO_CHARS)),
            Value::Empty => "an empty value".to_owned(),
            Value::Seq(items) => format!("a sequence of {} items", items.len()),
            Value::Map(entries) => format!("a map with {} keys", entries.len()),
        }
    }
}

/// Parses a FileStorage file's text: XML when `xml` is true, YAML otherwise. The top level must be
/// a map (OpenCV's root node); errors name `path` and the line.
pub(crate) fn parse(path: &Path, text: &str, xml: bool) -> Result<Value> {
    if xml {
        parse_xml(path, text)
    } else {
        parse_yaml(path, text)
    }
}

fn parse_yaml(path: &Path, text: &str) -> Result<Value> {
    // `%YAML:1.0` is OpenCV's own spelling of the directive (YAML 1.2 wants `%YAML 1.2`); the line
    // carries nothing else, so it is blanked and the line numbers stay those of the file.
    let body = match text.strip_prefix("%YAML:") {
        Some(rest) => format!("\n{}", rest.split_once('\n').map_or("", |(_, tail)| tail)),
        None => text.to_owned(),
    };
    refuse_aliases(path, &body)?;
    let docs = YamlLoader::load_from_str(&body).map_err(|e| not_yaml(path, &e))?;
    let Some(root) = docs.into_iter().next() else {
        return Err(syntax(
            path,
            0,
            "no YAML document (the file is empty or only comments): expected a map of calibration keys",
        ));
    };
    match from_yaml(path, root)? {
        map @ Value::Map(_) => Ok(map),
        other => Err(syntax(
            path,
            0,
            format!(
                "expected a map of calibration keys at the top level, found {}",
                other.describe()
            ),
        )),
    }
}

/// Notes the first alias (`*name`) of a YAML event stream.
#[derive(Default)]
struct FirstAlias(Option<Marker>);

impl MarkedEventReceiver for FirstAlias {
    fn on_event(&mut self, event: Event, mark: Marker) {
        if self.0.is_none() && matches!(event, Event::Alias(_)) {
            self.0 = Some(mark);
        }
    }
}

/// Refuses a file that uses YAML aliases, before it is loaded: the loader copies the anchored value
/// at every alias, so a few hundred bytes of aliases of aliases expand to gigabytes. OpenCV never
/// writes aliases, and a calibration has nothing to repeat.
fn refuse_aliases(path: &Path, body: &str) -> Result<()> {
    let mut first = FirstAlias::default();
    Parser::new_from_str(body)
        .load(&mut first, true)
        .map_err(|e| not_yaml(path, &e))?;
    match first.0 {
        Some(mark) => Err(syntax(
            path,
            mark.line(),
            "a YAML alias (*name): a calibration's values are written out, aliases are not read",
        )),
        None => Ok(()),
    }
}

fn not_yaml(path: &Path, e: &ScanError) -> crate::error::Error {
    syntax(path, e.marker().line(), format!("not valid YAML: {}", e.info()))
}

fn from_yaml(path: &Path, y: Yaml) -> Result<Value> {
    Ok(match y {
        Yaml::Real(s) => match parse_number(&s) {
            Some(v) => Value::Number(v),
            None => Value::Text(s),
        },
        // Every i64 is a double to OpenCV too (rounded past 2^53).
        #[allow(clippy::cast_precision_loss)]
        Yaml::Integer(i) => Value::Number(i as f64),
        Yaml::String(s) => Value::Text(s),
        Yaml::Boolean(b) => Value::Text(b.to_string()),
        Yaml::Null => Value::Empty,
        Yaml::Array(items) => Value::Seq(
            items
                .into_iter()
                .map(|v| from_yaml(path, v))
                .collect::<Result<_>>()?,
        ),
        Yaml::Hash(map) => {
            let mut entries = Vec::with_capacity(map.len());
            for (k, v) in map {
                let key = match k {
                    Yaml::String(s) => s,
                    Yaml::Integer(i) => i.to_string(),
                    Yaml::Real(s) => s,
                    other => {
                        return Err(syntax(
                            path,
                            0,
                            format!("a map key that is not a name: {other:?}"),
                        ));
                    }
                };
                entries.push((key, from_yaml(path, v)?));
            }
            Value::Map(entries)
        }
        Yaml::Alias(_) => return Err(syntax(path, 0, "YAML aliases are not supported in a calibration")),
        Yaml::BadValue => return Err(syntax(path, 0, "a value YAML cannot read")),
    })
}

/// A number as OpenCV writes or reads one: Rust's float syntax (`1.`, `1e-3`, `+2`) plus YAML's
/// `.nan` / `.inf` spellings, so that non-finite values are reported as such rather than as text.
fn parse_number(s: &str) -> Option<f64> {
    let t = s.trim();
    match t.to_ascii_lowercase().as_str() {
        ".nan" => return Some(f64::NAN),
        ".inf" | "+.inf" => return Some(f64::INFINITY),
        "-.inf" => return Some(f64::NEG_INFINITY),
        _ => {}
    }
    // Rust also accepts "inf", "infinity" and "nan" words; OpenCV would read them as strings.
    if t.chars().any(|c| c.is_ascii_alphabetic() && c != 'e' && c != 'E') {
        return None;
    }
    t.parse::<f64>().ok()
}

fn parse_xml(path: &Path, text: &str) -> Result<Value> {
    let options = ParsingOptions {
        nodes_limit: MAX_XML_NODES,
        ..ParsingOptions::default()
    };
    let doc = Document::parse_with_options(text, options).map_err(|e| {
        let line = usize::try_from(e.pos().row).unwrap_or(0);
        syntax(path, line, format!("not valid XML: {e}"))
    })?;
    let root = doc.root_element();
    if root.tag_name().name() != "opencv_storage" {
        return Err(syntax(
            path,
            line_of(&doc, root),
            format!(
                "the root element is <{}>: expected <opencv_storage>",
                root.tag_name().name()
            ),
        ));
    }
    Ok(from_xml(root))
}

fn line_of(doc: &Document<'_>, node: roxmltree::Node<'_, '_>) -> usize {
    usize::try_from(doc.text_pos_at(node.range().start).row).unwrap_or(0)
}

fn from_xml(element: roxmltree::Node<'_, '_>) -> Value {
    let children: Vec<_> = element.children().filter(roxmltree::Node::is_element).collect();
    if children.is_empty() {
        let text: String = element.children().filter_map(|n| n.text()).collect();
        return xml_text(&text);
    }
    if children.iter().all(|c| c.tag_name().name() == "_") {
        return Value::Seq(children.into_iter().map(|c| from_xml(c)).collect());
    }
    Value::Map(
        children
            .into_iter()
            .map(|c| (c.tag_name().name().to_owned(), from_xml(c)))
            .collect(),
    )
}

/// An element's text: one number, several numbers (a sequence, as OpenCV writes short vectors and a
/// matrix's `data`), or a string (quotes removed).
fn xml_text(text: &str) -> Value {
    let words: Vec<&str> = text.split_whitespace().collect();
    if words.is_empty() {
        return Value::Empty;
    }
    let numbers: Option<Vec<f64>> = words.iter().map(|w| parse_number(w)).collect();
    match numbers {
        Some(v) if v.len() == 1 => Value::Number(v[0]),
        Some(v) => Value::Seq(v.into_iter().map(Value::Number).collect()),
        None => Value::Text(text.trim().trim_matches('"').to_owned()),
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    fn yaml(text: &str) -> Result<Value> {
        parse(Path::new("c.yaml"), text, false)
    }

    fn xml(text: &str) -> Result<Value> {
        parse(Path::new("c.xml"), text, true)
    }

    #[test]
    fn opencv_yaml_matrices_numbers_and_sequences() {
        let v = yaml(
            "%YAML:1.0\n---\nK1: !!opencv-matrix\n   rows: 1\n   cols: 2\n   dt: d\n   data: [ 1., -2.5e+02 ]\n\
             image_width: 640\nsize: [640, 480]\nname: \"left\"\nbad: .NaN\n",
        )
        .unwrap();
        let k1 = v.get("K1").unwrap();
        assert_eq!(k1.get("rows"), Some(&Value::Number(1.0)));
        assert_eq!(
            k1.get("data"),
            Some(&Value::Seq(vec![Value::Number(1.0), Value::Number(-250.0)]))
        );
        assert_eq!(v.get("image_width"), Some(&Value::Number(640.0)));
        assert_eq!(v.get("name"), Some(&Value::Text("left".to_owned())));
        assert!(matches!(v.get("bad"), Some(Value::Number(x)) if x.is_nan()));
    }

    #[test]
    fn opencv_xml_matrices_numbers_and_sequences() {
        let v = xml(
            "<?xml version=\"1.0\"?>\n<opencv_storage>\n<K1 type_id=\"opencv-matrix\"><rows>1</rows>\
             <cols>2</cols><dt>d</dt><data>\n 1. -2.5e+02</data></K1>\n<w>640</w><s>640 480</s>\
             <q><_>1</_><_>2</_></q><n>\"left\"</n><e/></opencv_storage>\n",
        )
        .unwrap();
        assert_eq!(
            v.get("K1").unwrap().get("data"),
            Some(&Value::Seq(vec![Value::Number(1.0), Value::Number(-250.0)]))
        );
        assert_eq!(v.get("w"), Some(&Value::Number(640.0)));
        assert_eq!(
            v.get("s"),
            Some(&Value::Seq(vec![Value::Number(640.0), Value::Number(480.0)]))
        );
        assert_eq!(
            v.get("q"),
            Some(&Value::Seq(vec![Value::Number(1.0), Value::Number(2.0)]))
        );
        assert_eq!(v.get("n"), Some(&Value::Text("left".to_owned())));
        assert_eq!(v.get("e"), Some(&Value::Empty));
    }

    #[test]
    fn syntax_errors_name_the_file_and_line() {
        let e = yaml("%YAML:1.0\n---\nK1: [1, 2\nD1: 3\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("c.yaml") && e.contains("YAML"), "{e}");
        let e = xml("<?xml version=\"1.0\"?>\n<opencv_storage>\n<K1>1</K2>\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("c.xml") && e.contains("line 3"), "{e}");
        let e = xml("<?xml version=\"1.0\"?>\n<storage/>\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("opencv_storage"), "{e}");
        let e = yaml("- 1\n- 2\n").unwrap_err().to_string();
        assert!(e.contains("top level"), "{e}");
    }

    #[test]
    fn words_that_rust_reads_as_floats_stay_text() {
        for w in ["inf", "NaN", "infinity", "e", "1e"] {
            assert!(!matches!(xml_text(w), Value::Number(_)), "{w}");
        }
        assert_eq!(xml_text(" 1. "), Value::Number(1.0));
        assert_eq!(xml_text("-.Inf"), Value::Number(f64::NEG_INFINITY));
    }
}
