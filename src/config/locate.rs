//! The one locator: a key path (`camera[1].fx`, `specimen.beam.span_mm`, `gauge[0].tags`) to
//! the line it is written on, read from the TOML document's own spans.
//!
//! Components report problems by key path only ([`tagdeflect_core::Problem`]); this turns the
//! path into `file:line`. A key that is not written (a missing or defaulted value) is placed
//! on the line of the deepest table of its path that is written — the table the key belongs
//! in — and a path of which nothing is written has no line.

use std::ops::Range;

use toml_edit::{ImDocument, Item, Table, Value};

/// One step of a key path.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Step<'a> {
    Key(&'a str),
    Index(usize),
}

/// Splits `a.b[2].c` into keys and indices.
fn steps(path: &str) -> Vec<Step<'_>> {
    let mut out = Vec::new();
    for part in path.split('.') {
        let (key, mut rest) = match part.find('[') {
            Some(i) => (&part[..i], &part[i..]),
            None => (part, ""),
        };
        if !key.is_empty() {
            out.push(Step::Key(key));
        }
        while let Some(r) = rest.strip_prefix('[') {
            let Some(end) = r.find(']') else { break };
            if let Ok(i) = r[..end].parse() {
                out.push(Step::Index(i));
            }
            rest = &r[end + 1..];
        }
    }
    out
}

/// Where a config's keys are written.
pub struct Locator<'a> {
    text: &'a str,
    doc: Option<ImDocument<&'a str>>,
}

/// A node of the document while a path is walked.
enum Node<'d> {
    Table(&'d Table),
    Item(&'d Item),
    Value(&'d Value),
}

impl<'a> Locator<'a> {
    /// Reads the spans of `text` (a text that does not parse has no spans: every problem of
    /// it is then reported without a line).
    pub fn new(text: &'a str) -> Self {
        Self { text, doc: ImDocument::parse(text).ok() }
    }

    /// The byte span where `path` (or the deepest written table of it) is written.
    pub fn span(&self, path: &str) -> Option<Range<usize>> {
        let doc = self.doc.as_ref()?;
        let mut node = Node::Table(doc.as_table());
        let mut best: Option<Range<usize>> = None;
        for step in steps(path) {
            let next: Option<(Node<'_>, Option<Range<usize>>)> = match (&node, step) {
                (Node::Table(t), Step::Key(k)) => {
                    t.get_key_value(k).map(|(key, item)| (Node::Item(item), key.span().or_else(|| item.span())))
                }
                (Node::Item(Item::Table(t)), Step::Key(k)) => {
                    t.get_key_value(k).map(|(key, item)| (Node::Item(item), key.span().or_else(|| item.span())))
                }
                (Node::Item(Item::ArrayOfTables(a)), Step::Index(i)) => a.get(i).map(|t| (Node::Table(t), t.span())),
                (Node::Item(Item::ArrayOfTables(a)), Step::Key(k)) => {
                    // `specimen.tag.id`: a key of the array's tables, none named: the first
                    // table that has it.
                    a.iter().find_map(|t| t.get_key_value(k)).map(|(key, item)| (Node::Item(item), key.span().or_else(|| item.span())))
                }
                (Node::Item(Item::Value(v)), s) => value_step(v, s),
                (Node::Value(v), s) => value_step(v, s),
                _ => None,
            };
            match next {
                Some((n, span)) => {
                    if span.is_some() {
                        best = span;
                    }
                    node = n;
                }
                None => break,
            }
        }
        best
    }

    /// The 1-based line where `path` is written (see the module doc).
    pub fn line(&self, path: &str) -> Option<usize> {
        self.span(path).map(|s| self.line_of(s.start))
    }

    /// The 1-based line holding byte offset `at`.
    pub fn line_of(&self, at: usize) -> usize {
        let end = at.min(self.text.len());
        self.text[..end].bytes().filter(|&b| b == b'\n').count() + 1
    }
}

fn value_step<'d>(v: &'d Value, step: Step<'_>) -> Option<(Node<'d>, Option<Range<usize>>)> {
    match (v, step) {
        (Value::InlineTable(t), Step::Key(k)) => {
            t.get_key_value(k).map(|(key, item)| (Node::Item(item), key.span().or_else(|| item.span())))
        }
        (Value::Array(a), Step::Index(i)) => a.get(i).map(|v| (Node::Value(v), v.span())),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TEXT: &str = "[world]\nup = [0, 0, 1]\n\n[[camera]]\nname = \"a\"\n\n[[camera]]\nname = \"b\"\nfx = 10\n\n[specimen]\nfamily = \"tag36h11\"\n[specimen.beam]\nspan_mm = 3\n\n[[specimen.tag]]\nid = 1\n[[specimen.tag]]\nid = 2\nrole = \"midspan\"\n\n[output.mqtt]\nurl = \"mqtt://x\"\n[utm]\nload = { register = 0, scale = 0 }\n";

    #[test]
    fn a_key_path_finds_its_line() {
        let l = Locator::new(TEXT);
        assert_eq!(l.line("world.up"), Some(2));
        assert_eq!(l.line("camera[1].fx"), Some(9));
        assert_eq!(l.line("camera[0].name"), Some(5));
        assert_eq!(l.line("specimen.beam.span_mm"), Some(14));
        assert_eq!(l.line("specimen.tag[1].role"), Some(20));
        assert_eq!(l.line("output.mqtt.url"), Some(23));
        assert_eq!(l.line("utm.load.scale"), Some(25));
        assert_eq!(l.line("specimen.tag.id"), Some(17));
    }

    #[test]
    fn an_unwritten_key_is_placed_on_its_table() {
        let l = Locator::new(TEXT);
        assert_eq!(l.line("camera[0].fx"), Some(4));
        assert_eq!(l.line("specimen.beam.width_mm"), Some(13));
        assert_eq!(l.line("measure.quad_decimate"), None);
        assert_eq!(l.line("camera[7].fx"), Some(4));
    }

    #[test]
    fn paths_split_into_keys_and_indices() {
        assert_eq!(steps("a[2].b"), vec![Step::Key("a"), Step::Index(2), Step::Key("b")]);
        assert_eq!(steps("gauge[0]"), vec![Step::Key("gauge"), Step::Index(0)]);
        assert_eq!(steps(""), Vec::<Step<'_>>::new());
    }
}
