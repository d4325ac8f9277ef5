//! The settings page (docs/settings.md): every setting of the product's configurations, its value in
//! each preset and its meaning, rendered from the code so that the page cannot drift from it.
//!
//! The values come from the configurations' pretty `Debug` output (`{:#?}`), the meanings from the
//! doc comments above the fields in the sources; a field is documented once, in the code. A number
//! a doc comment quotes as its default ("default 0.5", "outdoor 1.0, indoor 0.3") is checked
//! against the value the code sets ([`check_quoted_defaults`]). No I/O: the caller hands in the
//! sources and the rendered configurations.

use std::collections::{BTreeMap, HashMap};
use std::fmt::Write;

/// One Rust source file: where it is (for messages and links) and its text.
#[derive(Clone, Copy, Debug)]
pub struct Source<'a> {
    pub path: &'a str,
    pub text: &'a str,
}

/// Where a field is documented: its struct and its name.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct FieldKey {
    pub owner: String,
    pub field: String,
}

/// A field's doc comment and the file it is in.
#[derive(Clone, Debug, PartialEq)]
pub struct FieldDoc {
    pub path: String,
    pub line: usize,
    pub doc: String,
}

/// The doc comments of every named-field struct's public fields in `sources`.
pub fn field_docs(sources: &[Source]) -> HashMap<FieldKey, FieldDoc> {
    let mut docs = HashMap::new();
    for source in sources {
        let mut owner: Option<String> = None;
        let mut doc: Vec<&str> = Vec::new();
        for (index, raw) in source.text.lines().enumerate() {
            let line = raw.trim();
            if let Some(name) = struct_opening(line) {
                owner = Some(name.to_string());
                doc.clear();
                continue;
            }
            let Some(current) = owner.as_ref() else { continue };
            if raw.starts_with('}') {
                owner = None;
            } else if let Some(text) = line.strip_prefix("///") {
                doc.push(text.trim());
            } else if let Some(field) = field_name(line) {
                docs.insert(
                    FieldKey { owner: current.clone(), field: field.to_string() },
                    FieldDoc { path: source.path.to_string(), line: index + 1, doc: doc.join(" ") },
                );
                doc.clear();
            } else if !line.starts_with("#[") {
                doc.clear();
            }
        }
    }
    docs
}

/// `pub struct Name {` (generics and where clauses aside, which configurations do not have).
fn struct_opening(line: &str) -> Option<&str> {
    let rest = line.strip_prefix("pub struct ")?.strip_suffix('{')?.trim();
    rest.chars().all(|c| c.is_alphanumeric() || c == '_').then_some(rest)
}

/// `pub name: Type,`
fn field_name(line: &str) -> Option<&str> {
    let rest = line.strip_prefix("pub ")?;
    let (name, _) = rest.split_once(':')?;
    name.chars().all(|c| c.is_alphanumeric() || c == '_').then_some(name)
}

/// One setting of a rendered configuration: its dotted path from the root, the struct field it is,
/// and its value as `Debug` writes it (compacted to one line).
#[derive(Clone, Debug, PartialEq)]
pub struct Setting {
    pub path: String,
    pub key: FieldKey,
    pub value: String,
}

/// A line of pretty `Debug` output, or a block it opens (`{`, `(` or `[`) with what it holds.
#[derive(Clone, Debug)]
enum Item {
    Line(String),
    Block { head: String, open: char, items: Vec<Item> },
}

fn parse_items(lines: &mut std::str::Lines) -> Vec<Item> {
    let mut items = Vec::new();
    while let Some(raw) = lines.next() {
        let line = raw.trim().trim_end_matches(',');
        if matches!(line, "}" | ")" | "]") {
            break;
        }
        match line.chars().last() {
            Some(open @ ('{' | '(' | '[')) => {
                let head = line[..line.len() - 1].trim().to_string();
                let inner = parse_items(lines);
                items.push(Item::Block { head, open, items: inner });
            }
            _ => items.push(Item::Line(line.to_string())),
        }
    }
    items
}

fn compact(item: &Item) -> String {
    match item {
        Item::Line(line) => line.clone(),
        Item::Block { head, open, items } => {
            let close = match open {
                '{' => '}',
                '(' => ')',
                _ => ']',
            };
            let inner: Vec<String> = items.iter().map(compact).collect();
            let separator = if head.is_empty() { "" } else { " " };
            match open {
                '{' => format!("{head}{separator}{{ {} }}", inner.join(", ")),
                _ => format!("{head}{open}{}{close}", inner.join(", ")),
            }
        }
    }
}

/// Every setting of a configuration from its pretty `Debug` output (`format!("{config:#?}")`).
/// A field holding another struct whose fields are documented in `docs` (directly or inside
/// `Some(..)`) is followed into; any other value is one setting.
pub fn settings(debug: &str, docs: &HashMap<FieldKey, FieldDoc>) -> Vec<Setting> {
    let items = parse_items(&mut debug.lines());
    let mut out = Vec::new();
    if let Some(Item::Block { head, items, .. }) = items.first() {
        walk(head, items, "", docs, &mut out);
    }
    out
}

fn documented(owner: &str, docs: &HashMap<FieldKey, FieldDoc>) -> bool {
    docs.keys().any(|key| key.owner == owner)
}

fn walk(owner: &str, items: &[Item], prefix: &str, docs: &HashMap<FieldKey, FieldDoc>, out: &mut Vec<Setting>) {
    for item in items {
        let (field, value) = match item {
            Item::Line(line) => match line.split_once(": ") {
                Some((field, value)) => (field, value.to_string()),
                None => continue,
            },
            Item::Block { head, open, items } => {
                let Some((field, inner_head)) = head.split_once(": ") else { continue };
                let path = format!("{prefix}{field}.");
                if *open == '{' && documented(inner_head, docs) {
                    walk(inner_head, items, &path, docs, out);
                    continue;
                }
                if let (true, "Some", [Item::Block { head: inner, open: '{', items }]) =
                    (*open == '(', inner_head, items.as_slice())
                    && documented(inner, docs)
                {
                    walk(inner, items, &path, docs, out);
                    continue;
                }
                let block = Item::Block { head: inner_head.to_string(), open: *open, items: items.clone() };
                (field, compact(&block))
            }
        };
        out.push(Setting {
            path: format!("{prefix}{field}"),
            key: FieldKey { owner: owner.to_string(), field: field.to_string() },
            value,
        });
    }
}

/// A configuration on the page: a title, and its settings in each named preset (one type, though an
/// optional part may be set in one preset only; the table lines them up by path).
pub struct Section<'a> {
    pub title: &'a str,
    /// What the configuration is and where it is chosen (one paragraph).
    pub intro: &'a str,
    /// The presets' names and their pretty `Debug` outputs.
    pub presets: Vec<(&'a str, String)>,
}

/// A setting that breaks the page's rules.
#[derive(Clone, Debug, PartialEq)]
pub enum Problem {
    /// A field with no doc comment.
    Undocumented { path: String, key: FieldKey },
    /// A doc comment quotes a default the code does not set.
    QuotedDefault { key: FieldKey, at: String, quoted: String, value: String },
}

impl std::fmt::Display for Problem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Problem::Undocumented { path, key } => {
                write!(f, "{path} ({}::{}) has no doc comment", key.owner, key.field)
            }
            Problem::QuotedDefault { key, at, quoted, value } => {
                write!(f, "{at}: {}::{} says its default is {quoted}, the code sets {value}", key.owner, key.field)
            }
        }
    }
}

/// The page: per section a table of every setting, its value in each preset and the first
/// sentence of its doc comment (the rest, the reason, is in the code the link points at).
/// `link_root` leads from the page to the sources' root (`../` for a page in docs/).
pub fn render(sections: &[Section], docs: &HashMap<FieldKey, FieldDoc>, link_root: &str) -> (String, Vec<Problem>) {
    let mut page = String::new();
    let mut problems = Vec::new();
    for section in sections {
        let _ = writeln!(page, "## {}\n\n{}\n", section.title, section.intro);
        let columns: Vec<Vec<Setting>> = section.presets.iter().map(|(_, debug)| settings(debug, docs)).collect();
        let names: Vec<&str> = section.presets.iter().map(|(name, _)| *name).collect();
        let _ = writeln!(page, "| setting | {} | meaning |", names.join(" | "));
        let _ = writeln!(page, "|---|{}---|", "---|".repeat(names.len()));
        for setting in rows(&columns) {
            let values: Vec<String> = columns
                .iter()
                .map(|column| match column.iter().find(|s| s.path == setting.path) {
                    Some(s) => format!("`{}`", cell(&s.value)),
                    None => "-".to_string(),
                })
                .collect();
            let meaning = match docs.get(&setting.key) {
                Some(doc) if !doc.doc.is_empty() => {
                    format!("{} ([code]({link_root}{}#L{}))", cell(first_sentence(&doc.doc)), doc.path, doc.line)
                }
                _ => {
                    problems.push(Problem::Undocumented { path: setting.path.clone(), key: setting.key.clone() });
                    String::new()
                }
            };
            let _ = writeln!(page, "| `{}` | {} | {meaning} |", setting.path, values.join(" | "));
        }
        page.push('\n');
    }
    (page, problems)
}

/// The rows of a table whose presets may differ in shape (an optional part set in one preset
/// only): every path of every preset once, each after the path it follows in its own preset.
fn rows(columns: &[Vec<Setting>]) -> Vec<&Setting> {
    let mut rows: Vec<&Setting> = Vec::new();
    for column in columns {
        let mut at = 0;
        for setting in column {
            match rows.iter().position(|row| row.path == setting.path) {
                Some(found) => at = found + 1,
                None => {
                    rows.insert(at, setting);
                    at += 1;
                }
            }
        }
    }
    rows
}

fn cell(text: &str) -> String {
    text.replace('|', "\\|")
}

/// Up to the first full stop that ends a sentence (not one inside a number or an abbreviation
/// such as "e.g.").
pub fn first_sentence(doc: &str) -> &str {
    let bytes = doc.as_bytes();
    let mut depth = 0i32;
    for (i, &b) in bytes.iter().enumerate() {
        match b {
            b'(' | b'[' => depth += 1,
            b')' | b']' => depth -= 1,
            b'.' if depth <= 0 && bytes.get(i + 1).is_none_or(|c| *c == b' ') => {
                let before = &doc[..i];
                if !(before.ends_with("e.g") || before.ends_with("i.e") || before.ends_with(" vs")) {
                    return &doc[..=i];
                }
            }
            _ => {}
        }
    }
    doc
}

/// Numbers the doc comments quote as defaults, checked against the code: "(default X" against
/// the setting's value in every preset of the section that renders it when all presets agree,
/// "NAME X" for a preset's NAME (e.g. "outdoor 1.0, indoor 0.3") against that preset. Only plain
/// numbers, `None`, `true` and `false` are compared; "default [`Type::fn`]" and prose are not.
/// `type_defaults` are the `Default` renderings of types used under several paths with different
/// values (a registration's settings differ where it is used): their fields' "(default X" is checked
/// against these instead.
pub fn check_quoted_defaults(
    sections: &[Section],
    type_defaults: &[String],
    docs: &HashMap<FieldKey, FieldDoc>,
) -> Vec<Problem> {
    let mut problems = Vec::new();
    let mut by_type: HashMap<FieldKey, String> = HashMap::new();
    let mut owners_with_default = std::collections::HashSet::new();
    for debug in type_defaults {
        for setting in settings(debug, docs).into_iter().filter(|s| !s.path.contains('.')) {
            owners_with_default.insert(setting.key.owner.clone());
            by_type.insert(setting.key, setting.value);
        }
    }
    // Per field: its values under each preset's name (every path it appears at).
    let mut seen: BTreeMap<FieldKey, Vec<(String, String)>> = BTreeMap::new();
    for section in sections {
        for (name, debug) in &section.presets {
            for setting in settings(debug, docs) {
                seen.entry(setting.key).or_default().push((name.to_string(), setting.value));
            }
        }
    }
    for (key, values) in &seen {
        let Some(doc) = docs.get(key) else { continue };
        let at = format!("{}:{}", doc.path, doc.line);
        if let Some(quoted) = quoted_after(&doc.doc, "default") {
            let expected: Vec<&String> = if owners_with_default.contains(&key.owner) {
                by_type.get(key).into_iter().collect()
            } else {
                values.iter().map(|(_, v)| v).collect()
            };
            if let Some(value) = expected.iter().find(|v| !same_value(&quoted, v)) {
                problems.push(Problem::QuotedDefault {
                    key: key.clone(),
                    at: at.clone(),
                    quoted,
                    value: (*value).clone(),
                });
            }
        }
        // A type used at several paths of one preset (the merge's fine and coarse pairwise
        // settings) is right when one of them has the quoted value.
        let names: std::collections::BTreeSet<&String> = values.iter().map(|(name, _)| name).collect();
        for name in names.into_iter().filter(|name| *name != "default") {
            let Some(quoted) = quoted_after(&doc.doc, name) else { continue };
            let in_preset: Vec<&String> = values.iter().filter(|(n, _)| n == name).map(|(_, v)| v).collect();
            if !in_preset.iter().any(|v| same_value(&quoted, v)) {
                problems.push(Problem::QuotedDefault {
                    key: key.clone(),
                    at: at.clone(),
                    quoted: format!("{name} {quoted}"),
                    value: in_preset.iter().map(|v| v.as_str()).collect::<Vec<_>>().join(" or "),
                });
            }
        }
    }
    problems.dedup();
    problems
}

/// The first word after "(WORD ", ", WORD ", "; WORD " or a sentence's "WORD " (capitalised) when
/// it is a number, None, true or false.
fn quoted_after(doc: &str, word: &str) -> Option<String> {
    let mut capital = word.to_string();
    capital[..1].make_ascii_uppercase();
    let patterns = [
        format!("({word} "),
        format!(", {word} "),
        format!("; {word} "),
        format!(". {capital} "),
        format!(": {capital} "),
    ];
    let padded = format!(". {doc}");
    for pattern in &patterns {
        let mut rest = padded.as_str();
        while let Some(at) = rest.find(pattern.as_str()) {
            let after = &rest[at + pattern.len()..];
            // "5,000": a comma between digits groups thousands.
            let chars: Vec<char> = after.chars().collect();
            let taken = chars
                .iter()
                .enumerate()
                .take_while(|&(i, c)| {
                    c.is_ascii_alphanumeric()
                        || matches!(c, '.' | '-' | '_' | '`')
                        || (matches!(c, ',' | ' ') && thousands(&chars, i))
                })
                .count();
            let token: String = chars[..taken].iter().filter(|c| !matches!(c, ',' | ' ')).collect();
            let token = token.trim_matches('`').trim_end_matches('.').to_string();
            // "2 × voxel = 0.8": a factor, not the value.
            let next = chars[taken..].iter().find(|c| **c != ' ');
            if matches!(next, Some('×' | '*')) {
                rest = after;
                continue;
            }
            if token.parse::<f64>().is_ok() || matches!(token.as_str(), "None" | "true" | "false") {
                return Some(token);
            }
            rest = after;
        }
    }
    None
}

/// A separator at `i` between a digit and a group of exactly three digits ("5,000", "20 000").
fn thousands(chars: &[char], i: usize) -> bool {
    let digit = |j: usize| chars.get(j).is_some_and(char::is_ascii_digit);
    i > 0 && digit(i - 1) && (1..=3).all(|k| digit(i + k)) && !digit(i + 4)
}

/// A quoted number is the code's value rounded to the quoted digits ("1.745e-3" for
/// 0.0017453292519943296, "0.3" for an f32's 0.30000001192092896).
fn same_value(quoted: &str, value: &str) -> bool {
    match (quoted.parse::<f64>(), value.parse::<f64>()) {
        (Ok(a), Ok(b)) => {
            let (mantissa, exponent) = quoted.split_once(['e', 'E']).unwrap_or((quoted, "0"));
            let decimals = mantissa.split_once('.').map_or(0, |(_, d)| d.len()) as i32;
            let unit = 10f64.powi(exponent.parse::<i32>().unwrap_or(0) - decimals);
            (a - b).abs() <= unit / 2.0 + 1e-12 * b.abs()
        }
        _ => quoted == value,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SOURCE: &str = r#"
/// Outer.
pub struct OuterConfig {
    /// Voxel, metres (outdoor 0.4, indoor 0.1). Finer indoors.
    pub voxel: f32,
    /// The inner part.
    pub inner: InnerConfig,
    /// An optional part (default None).
    pub maybe: Option<InnerConfig>,
    pub bare: usize,
}

#[derive(Debug)]
pub struct InnerConfig {
    /// Iterations (default 10).
    #[serde(default)]
    pub iterations: usize,
    /// A kernel, e.g. Huber. Robust.
    pub kernel: Kernel,
}
"#;

    fn debug(voxel: &str, iterations: usize, maybe: bool) -> String {
        let maybe = if maybe {
            format!(
                "Some(\n        InnerConfig {{\n            iterations: {iterations},\n            kernel: Cauchy,\n        }},\n    )"
            )
        } else {
            "None".to_string()
        };
        format!(
            "OuterConfig {{\n    voxel: {voxel},\n    inner: InnerConfig {{\n        iterations: {iterations},\n        kernel: Huber(\n            1.5,\n        ),\n    }},\n    maybe: {maybe},\n    bare: 3,\n}}"
        )
    }

    fn docs() -> HashMap<FieldKey, FieldDoc> {
        field_docs(&[Source { path: "x.rs", text: SOURCE }])
    }

    #[test]
    fn docs_are_read_per_struct_and_field() {
        let docs = docs();
        let key = |o: &str, f: &str| FieldKey { owner: o.into(), field: f.into() };
        assert_eq!(docs[&key("OuterConfig", "voxel")].doc, "Voxel, metres (outdoor 0.4, indoor 0.1). Finer indoors.");
        assert_eq!(docs[&key("OuterConfig", "voxel")].line, 5);
        assert_eq!(docs[&key("InnerConfig", "iterations")].doc, "Iterations (default 10).");
        assert_eq!(docs[&key("OuterConfig", "bare")].doc, "");
        assert_eq!(docs.len(), 6);
    }

    #[test]
    fn settings_follow_documented_structs_and_compact_the_rest() {
        let found = settings(&debug("0.4", 10, true), &docs());
        let paths: Vec<(&str, &str)> = found.iter().map(|s| (s.path.as_str(), s.value.as_str())).collect();
        assert_eq!(
            paths,
            [
                ("voxel", "0.4"),
                ("inner.iterations", "10"),
                ("inner.kernel", "Huber(1.5)"),
                ("maybe.iterations", "10"),
                ("maybe.kernel", "Cauchy"),
                ("bare", "3"),
            ]
        );
        let none = settings(&debug("0.4", 10, false), &docs());
        assert_eq!(none[3].path, "maybe");
        assert_eq!(none[3].value, "None");
    }

    #[test]
    fn the_page_names_undocumented_fields_and_wrong_quoted_defaults() {
        let docs = docs();
        let section = |outdoor: &str, iterations| Section {
            title: "Outer",
            intro: "The outer settings.",
            presets: vec![("outdoor", debug(outdoor, iterations, false)), ("indoor", debug("0.1", iterations, false))],
        };
        let (page, problems) = render(&[section("0.4", 10)], &docs, "");
        assert!(
            page.contains("| `voxel` | `0.4` | `0.1` | Voxel, metres (outdoor 0.4, indoor 0.1). ([code](x.rs#L5)) |"),
            "{page}"
        );
        assert!(
            page.contains("| `inner.kernel` | `Huber(1.5)` | `Huber(1.5)` | A kernel, e.g. Huber. ([code]"),
            "{page}"
        );
        assert_eq!(problems.len(), 1, "{problems:?}");
        assert!(problems[0].to_string().contains("bare (OuterConfig::bare) has no doc comment"));

        assert!(check_quoted_defaults(&[section("0.4", 10)], &[], &docs).is_empty());
        let wrong = check_quoted_defaults(&[section("0.6", 12)], &[], &docs);
        let text: Vec<String> = wrong.iter().map(ToString::to_string).collect();
        assert_eq!(text.len(), 2, "{text:?}");
        assert!(
            text.iter().any(|t| t.contains("OuterConfig::voxel says its default is outdoor 0.4, the code sets 0.6"))
        );
        assert!(text.iter().any(|t| t.contains("InnerConfig::iterations says its default is 10, the code sets 12")));
    }

    #[test]
    fn presets_of_different_shapes_line_up_by_path() {
        let docs = docs();
        let section = Section {
            title: "Outer",
            intro: "",
            presets: vec![("outdoor", debug("0.4", 10, true)), ("indoor", debug("0.1", 10, false))],
        };
        let (page, _) = render(&[section], &docs, "../");
        let rows: Vec<&str> = page.lines().filter(|l| l.starts_with("| `")).collect();
        let cells = |row: &str| row.split(" | ").take(3).map(str::to_string).collect::<Vec<_>>().join(" | ");
        let got: Vec<String> = rows.iter().map(|r| cells(r)).collect();
        assert_eq!(
            got,
            [
                "| `voxel` | `0.4` | `0.1`",
                "| `inner.iterations` | `10` | `10`",
                "| `inner.kernel` | `Huber(1.5)` | `Huber(1.5)`",
                "| `maybe` | - | `None`",
                "| `maybe.iterations` | `10` | -",
                "| `maybe.kernel` | `Cauchy` | -",
                "| `bare` | `3` | `3`",
            ]
        );
        assert!(page.contains("([code](../x.rs#L5))"), "{page}");
    }

    #[test]
    fn a_type_default_judges_its_own_fields() {
        let docs = docs();
        let section = Section { title: "Outer", intro: "", presets: vec![("default", debug("0.4", 12, false))] };
        let inner = "InnerConfig {\n    iterations: 10,\n    kernel: Cauchy,\n}".to_string();
        assert!(check_quoted_defaults(&[section], &[inner], &docs).is_empty());
    }

    #[test]
    fn quoted_numbers_are_rounded_values() {
        assert!(same_value("1.745e-3", "0.0017453292519943296"));
        assert!(same_value("0.3", "0.30000001192092896"));
        assert!(same_value("20000", "20000"));
        assert!(!same_value("1", "0.001"));
        assert!(!same_value("0.1", "0.2"));
        assert!(!same_value("1.74e-3", "0.0017453292519943296"));
        assert!(same_value("None", "None") && !same_value("None", "Some(1)"));
    }

    #[test]
    fn sentences_end_at_a_full_stop_outside_brackets() {
        assert_eq!(first_sentence("Voxel (0.5 m. or so). Rest."), "Voxel (0.5 m. or so).");
        assert_eq!(first_sentence("A kernel, e.g. Huber. Robust."), "A kernel, e.g. Huber.");
        assert_eq!(first_sentence("No stop"), "No stop");
    }

    #[test]
    fn quoted_defaults_are_numbers_after_their_word() {
        assert_eq!(quoted_after("Cap (default 20 000; each", "default").as_deref(), Some("20000"));
        assert_eq!(quoted_after("Samples (default 5,000).", "default").as_deref(), Some("5000"));
        assert_eq!(quoted_after("Radius (default 2 × voxel = 0.8, as", "default"), None);
        assert_eq!(quoted_after("Reach (default 1,000 × voxel)", "default"), None);
        assert_eq!(quoted_after("Inliers (default 10, 0 turns it off)", "default").as_deref(), Some("10"));
        assert_eq!(quoted_after("Voxel (outdoor 0.4, indoor 0.1).", "indoor").as_deref(), Some("0.1"));
        assert_eq!(quoted_after("Voxel (default [`Other::x`])", "default"), None);
        assert_eq!(quoted_after("Off (default None).", "default").as_deref(), Some("None"));
        assert_eq!(quoted_after("Gap (m). Default 0.3 m.", "default").as_deref(), Some("0.3"));
        assert_eq!(quoted_after("Default 1e-5 (GTSAM).", "default").as_deref(), Some("1e-5"));
        assert_eq!(quoted_after("Turned off by default 3 times.", "default"), None);
    }
}
