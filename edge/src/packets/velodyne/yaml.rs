//! The small part of YAML that velodyne_pointcloud's calibration files use, read line by line.
//!
//! A file is a mapping whose `lasers` key holds a sequence of mappings, each written either in
//! flow style (`- {laser_id: 0, rot_correction: 0.0, ...}`, possibly wrapped over several lines)
//! or in block style (`- laser_id: 0` followed by more-indented `key: value` lines). Other
//! top-level keys hold scalars (`distance_resolution: 0.002`) or nested blocks that are skipped
//! (the `status:` block velodyne_decoder writes). Anchors, multi-line strings and the like never
//! appear in these files and are not supported.

use super::calibration::CalibrationError;

/// One `key: value` pair and the line it was read from (1-based), for error messages.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct Entry {
    pub line: usize,
    pub key: String,
    pub value: String,
}

/// One item of the `lasers` sequence.
#[derive(Clone, Debug, Default, PartialEq)]
pub(super) struct Item {
    /// The line of the item's dash.
    pub line: usize,
    pub entries: Vec<Entry>,
}

/// The parts of a calibration file the decoder reads.
#[derive(Clone, Debug, Default, PartialEq)]
pub(super) struct Document {
    /// Top-level `key: value` pairs with a scalar value.
    pub scalars: Vec<Entry>,
    /// The `lasers` items, in file order; `None` when the file has no `lasers` key.
    pub lasers: Option<Vec<Item>>,
}

/// Where the reader is: at the top level, inside `lasers`, or skipping a nested block.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Section {
    Top,
    Lasers,
    Skipped,
}

/// Reads the calibration-file subset of YAML.
pub(super) fn parse(text: &str) -> Result<Document, CalibrationError> {
    let mut reader = Reader::default();
    for (index, raw) in text.lines().enumerate() {
        reader.line(index + 1, raw)?;
    }
    reader.finish()
}

#[derive(Default)]
struct Reader {
    document: Document,
    section: Option<Section>,
    /// The laser item being read and the indentation of its dash.
    item: Option<(Item, usize)>,
    /// A flow mapping (`{...}`) not yet closed: its text so far and its first line.
    flow: Option<(String, usize)>,
}

impl Reader {
    fn line(&mut self, number: usize, raw: &str) -> Result<(), CalibrationError> {
        let content = strip_comment(raw);
        if content.trim().is_empty() {
            return Ok(());
        }
        if content.starts_with('\t') {
            return Err(syntax(number, "tabs are not allowed for indentation"));
        }
        if let Some((text, start)) = self.flow.as_mut() {
            text.push(' ');
            text.push_str(content.trim());
            let start = *start;
            return self.close_flow_if_done(start);
        }
        let indent = content.len() - content.trim_start().len();
        let text = content.trim();
        let top_level_key = indent == 0 && !text.starts_with('-');
        if top_level_key {
            return self.top_level(number, text);
        }
        match self.section.unwrap_or(Section::Top) {
            Section::Lasers => self.laser_line(number, indent, text),
            Section::Skipped => Ok(()),
            Section::Top => Err(syntax(number, "an indented line or a list item outside any block")),
        }
    }

    fn top_level(&mut self, number: usize, text: &str) -> Result<(), CalibrationError> {
        self.end_item();
        let (key, value) = split_pair(number, text)?;
        self.section = Some(match (key.as_str(), value.is_empty()) {
            ("lasers", true) => {
                if self.document.lasers.is_some() {
                    return Err(syntax(number, "a second `lasers` key"));
                }
                self.document.lasers = Some(Vec::new());
                Section::Lasers
            }
            ("lasers", false) => return Err(syntax(number, "`lasers` must be followed by a list of lasers")),
            (_, true) => Section::Skipped,
            (_, false) => {
                self.document.scalars.push(Entry { line: number, key, value });
                Section::Top
            }
        });
        Ok(())
    }

    fn laser_line(&mut self, number: usize, indent: usize, text: &str) -> Result<(), CalibrationError> {
        if let Some(rest) = text.strip_prefix('-') {
            self.end_item();
            let rest = rest.trim();
            self.item = Some((Item { line: number, entries: Vec::new() }, indent));
            if rest.starts_with('{') {
                self.flow = Some((rest.to_string(), number));
                return self.close_flow_if_done(number);
            }
            if !rest.is_empty() {
                self.push_entry(number, rest)?;
            }
            return Ok(());
        }
        match &self.item {
            Some((_, dash_indent)) if indent > *dash_indent => self.push_entry(number, text),
            _ => Err(syntax(number, "a `key: value` line that belongs to no laser")),
        }
    }

    fn push_entry(&mut self, number: usize, text: &str) -> Result<(), CalibrationError> {
        let (key, value) = split_pair(number, text)?;
        if value.is_empty() {
            return Err(syntax(number, &format!("`{key}` has no value (nested blocks are not supported in a laser)")));
        }
        if let Some((item, _)) = self.item.as_mut() {
            item.entries.push(Entry { line: number, key, value });
        }
        Ok(())
    }

    /// Parses the pending flow mapping once its closing brace has been read.
    fn close_flow_if_done(&mut self, start: usize) -> Result<(), CalibrationError> {
        let Some((text, _)) = &self.flow else { return Ok(()) };
        let Some(close) = text.find('}') else { return Ok(()) };
        if !text[close + 1..].trim().is_empty() {
            return Err(syntax(start, "text after the closing `}` of a laser"));
        }
        let inner = text[1..close].to_string();
        self.flow = None;
        for pair in inner.split(',').map(str::trim).filter(|pair| !pair.is_empty()) {
            self.push_entry(start, pair)?;
        }
        self.end_item();
        Ok(())
    }

    fn end_item(&mut self) {
        if let Some((item, _)) = self.item.take()
            && let Some(lasers) = self.document.lasers.as_mut()
        {
            lasers.push(item);
        }
    }

    fn finish(mut self) -> Result<Document, CalibrationError> {
        if let Some((_, start)) = self.flow {
            return Err(syntax(start, "a laser's `{` is never closed"));
        }
        self.end_item();
        Ok(self.document)
    }
}

/// The line without its comment. A `#` starts a comment at the start of a line or after a space;
/// the values of these files never contain one.
fn strip_comment(line: &str) -> &str {
    let mut previous = ' ';
    for (at, character) in line.char_indices() {
        if character == '#' && previous.is_whitespace() {
            return &line[..at];
        }
        previous = character;
    }
    line
}

/// `key: value` into its trimmed, unquoted parts; the value may be empty (a nested block follows).
fn split_pair(number: usize, text: &str) -> Result<(String, String), CalibrationError> {
    let Some((key, value)) = text.split_once(':') else {
        return Err(syntax(number, &format!("expected `key: value`, found `{text}`")));
    };
    let key = unquote(key.trim());
    if key.is_empty() {
        return Err(syntax(number, "a value without a key"));
    }
    Ok((key.to_string(), unquote(value.trim()).to_string()))
}

fn unquote(text: &str) -> &str {
    for quote in ['"', '\''] {
        if let Some(inner) = text.strip_prefix(quote).and_then(|rest| rest.strip_suffix(quote)) {
            return inner;
        }
    }
    text
}

fn syntax(line: usize, reason: &str) -> CalibrationError {
    CalibrationError::Syntax { line, reason: reason.to_string() }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn keys(item: &Item) -> Vec<(&str, &str)> {
        item.entries.iter().map(|entry| (entry.key.as_str(), entry.value.as_str())).collect()
    }

    #[test]
    fn reads_wrapped_flow_items_and_top_level_scalars() {
        let text = "lasers:\n- {dist_correction: 0.0, laser_id: 0,\n  vert_correction: -0.26}\n\
                    - {laser_id: 1, vert_correction: 0.01}\nnum_lasers: 2\ndistance_resolution: 0.002\n";
        let document = parse(text).unwrap();
        let lasers = document.lasers.unwrap();
        assert_eq!(lasers.len(), 2);
        assert_eq!(keys(&lasers[0]), [("dist_correction", "0.0"), ("laser_id", "0"), ("vert_correction", "-0.26")]);
        assert_eq!(lasers[1].line, 4);
        assert_eq!(document.scalars.len(), 2);
        assert_eq!(document.scalars[1].key, "distance_resolution");
    }

    #[test]
    fn reads_block_items_and_skips_nested_blocks_and_comments() {
        let text = "# calibration\ndistance_resolution: 0.002 # metres\nlasers:\n  - laser_id: 0\n    \
                    rot_correction: 0.1\n  - laser_id: 1\n    rot_correction: -0.1\nstatus:\n  Model: S3\n  \
                    RPM: 600\nnum_lasers: 2\n";
        let document = parse(text).unwrap();
        let lasers = document.lasers.unwrap();
        assert_eq!(keys(&lasers[1]), [("laser_id", "1"), ("rot_correction", "-0.1")]);
        let scalars: Vec<_> = document.scalars.iter().map(|entry| entry.key.as_str()).collect();
        assert_eq!(scalars, ["distance_resolution", "num_lasers"]);
    }

    #[test]
    fn names_the_line_of_a_syntax_error() {
        let error = parse("lasers:\n- {laser_id: 0\n").unwrap_err();
        assert_eq!(error, CalibrationError::Syntax { line: 2, reason: "a laser's `{` is never closed".into() });
        let error = parse("lasers:\n- laser_id 0\n").unwrap_err();
        assert!(matches!(error, CalibrationError::Syntax { line: 2, .. }), "{error}");
    }
}
