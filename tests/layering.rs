//! The layering of `docs/architecture.md`, checked on the source: every `use` and every
//! `crate::`/`super::` path of the library is resolved (through re-exports) to the file that
//! defines what it names, and the resulting file graph must have no cycle, and no import
//! against the floors. Test modules (`#[cfg(test)]`) are left out: a test may reach anywhere.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The floors, lowest first: each top-level module of `src/` and the floors it may import
/// (its own module always may). A file named `error.rs` is on the base floor wherever it lies:
/// the crate's error wraps each module's error enum, which therefore imports nothing above.
const FLOORS: &[(&str, &[&str])] = &[
    ("base", &[]),
    ("numerics", &["base"]),
    ("data", &["base", "numerics"]),
    ("pipeline", &["base"]),
    ("domain", &["base", "numerics", "data", "pipeline"]),
    ("stages", &["base", "numerics", "data", "pipeline", "domain"]),
    ("top", &["base", "numerics", "data", "pipeline", "domain", "stages"]),
];

fn floor_of_module(top: &str) -> Option<&'static str> {
    Some(match top {
        "error" | "limits" | "parallel" | "allocator" | "progress" | "staging" | "sanity" | "fft2" => "base",
        "nufft" | "operator" | "weighting" | "deconv" | "metrics" | "primary_beam" => "numerics",
        "vis" | "fits" | "ms" => "data",
        "pipeline" => "pipeline",
        "imaging" | "simulate" | "job" | "steps" | "preview" => "domain",
        "stages" => "stages",
        "engine" | "request" | "bench" | "cli" | "parts" | "models" => "top",
        _ => return None,
    })
}

/// One source file as a module: its path in the crate (`["pipeline", "config"]`), its code
/// with comments, strings and test modules removed, and what it declares.
struct Module {
    file: PathBuf,
    code: String,
    /// Whether the file is a `mod.rs` or `lib.rs` (its `super` is its parent's parent).
    is_dir: bool,
    children: BTreeSet<String>,
    items: BTreeSet<String>,
    /// `pub use` re-exports: the name they give (`*` for a glob) and the absolute path.
    reexports: Vec<(String, Vec<String>)>,
    /// Every path the file names: absolute module paths (`crate`, `super`, `self` and
    /// child-module paths made absolute).
    paths: Vec<Vec<String>>,
}

fn strip(text: &str) -> String {
    let b = text.as_bytes();
    let mut out = String::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        let c = b[i];
        if c == b'/' && b.get(i + 1) == Some(&b'/') {
            while i < b.len() && b[i] != b'\n' {
                i += 1;
            }
        } else if c == b'/' && b.get(i + 1) == Some(&b'*') {
            let mut depth = 0;
            while i < b.len() {
                if b[i] == b'/' && b.get(i + 1) == Some(&b'*') {
                    depth += 1;
                    i += 2;
                } else if b[i] == b'*' && b.get(i + 1) == Some(&b'/') {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    i += 1;
                }
            }
        } else if c == b'r' && (b.get(i + 1) == Some(&b'"') || b.get(i + 1) == Some(&b'#')) && !is_ident(b.get(i.wrapping_sub(1)).copied()) {
            // Raw string r"..." or r#"..."#.
            let mut j = i + 1;
            let mut hashes = 0;
            while b.get(j) == Some(&b'#') {
                hashes += 1;
                j += 1;
            }
            if b.get(j) != Some(&b'"') {
                out.push(c as char);
                i += 1;
                continue;
            }
            j += 1;
            loop {
                if j >= b.len() {
                    break;
                }
                if b[j] == b'"' && (0..hashes).all(|h| b.get(j + 1 + h) == Some(&b'#')) {
                    j += 1 + hashes;
                    break;
                }
                j += 1;
            }
            out.push_str("\"\"");
            i = j;
        } else if c == b'"' {
            let mut j = i + 1;
            while j < b.len() && b[j] != b'"' {
                if b[j] == b'\\' {
                    j += 1;
                }
                j += 1;
            }
            out.push_str("\"\"");
            i = j + 1;
        } else if c == b'\'' {
            // A char literal ('x', '\n', '\u{1F}') or a lifetime ('a): only the former is cut.
            if b.get(i + 1) == Some(&b'\\') {
                let mut j = i + 2;
                while j < b.len() && b[j] != b'\'' {
                    j += 1;
                }
                out.push_str("' '");
                i = j + 1;
            } else if b.get(i + 2) == Some(&b'\'') {
                out.push_str("' '");
                i += 3;
            } else if i + 4 < b.len() && std::str::from_utf8(&b[i + 1..(i + 5).min(b.len())]).is_ok_and(|s| s.chars().nth(1) == Some('\'')) {
                // A multi-byte char literal.
                let len = std::str::from_utf8(&b[i + 1..]).map(|s| s.chars().next().map_or(1, char::len_utf8)).unwrap_or(1);
                out.push_str("' '");
                i += len + 2;
            } else {
                out.push('\'');
                i += 1;
            }
        } else {
            let ch_len = std::str::from_utf8(&b[i..]).ok().and_then(|s| s.chars().next()).map_or(1, char::len_utf8);
            out.push_str(&text[i..i + ch_len]);
            i += ch_len;
        }
    }
    out
}

fn is_ident(c: Option<u8>) -> bool {
    c.is_some_and(|c| c.is_ascii_alphanumeric() || c == b'_')
}

/// Removes every `#[cfg(test)]` item (a `mod tests { ... }`, a `mod tests;`, a function) and
/// returns the names of test-only child module files.
fn cut_tests(code: &str) -> (String, Vec<String>) {
    let mut code = code.to_string();
    let mut test_children = Vec::new();
    while let Some(at) = code.find("#[cfg(test)]") {
        let rest = &code[at..];
        let brace = rest.find('{');
        let semi = rest.find(';');
        let end = match (brace, semi) {
            (Some(b), Some(s)) if s < b => {
                if let Some(name) = rest[..s].split_whitespace().last() {
                    test_children.push(name.to_string());
                }
                at + s + 1
            }
            (Some(b), _) => {
                let bytes = code.as_bytes();
                let mut depth = 0;
                let mut j = at + b;
                loop {
                    match bytes[j] {
                        b'{' => depth += 1,
                        b'}' => {
                            depth -= 1;
                            if depth == 0 {
                                break;
                            }
                        }
                        _ => {}
                    }
                    j += 1;
                }
                j + 1
            }
            _ => code.len(),
        };
        code.replace_range(at..end, "");
    }
    (code, test_children)
}

/// The paths of a use tree (`a::{b, c::{self, d}}`), with the name each binds.
fn expand_use(tree: &str) -> Vec<(Vec<String>, String)> {
    fn split_top(s: &str) -> Vec<&str> {
        let mut parts = Vec::new();
        let (mut depth, mut start) = (0, 0);
        for (i, c) in s.char_indices() {
            match c {
                '{' => depth += 1,
                '}' => depth -= 1,
                ',' if depth == 0 => {
                    parts.push(&s[start..i]);
                    start = i + 1;
                }
                _ => {}
            }
        }
        parts.push(&s[start..]);
        parts
    }
    fn go(prefix: &[String], tree: &str, out: &mut Vec<(Vec<String>, String)>) {
        let tree = tree.trim();
        if tree.is_empty() {
            return;
        }
        if let Some(open) = tree.find('{') {
            let head: Vec<String> = tree[..open].split("::").map(str::trim).filter(|s| !s.is_empty()).map(String::from).collect();
            let inner = &tree[open + 1..tree.rfind('}').expect("balanced use tree")];
            let mut p = prefix.to_vec();
            p.extend(head);
            for part in split_top(inner) {
                go(&p, part, out);
            }
            return;
        }
        let (path, alias) = match tree.split_once(" as ") {
            Some((p, a)) => (p, Some(a.trim().to_string())),
            None => (tree, None),
        };
        let mut p = prefix.to_vec();
        p.extend(path.split("::").map(str::trim).filter(|s| !s.is_empty()).map(String::from));
        if p.last().is_some_and(|l| l == "self") {
            p.pop();
        }
        let name = alias.unwrap_or_else(|| p.last().cloned().unwrap_or_default());
        out.push((p, name));
    }
    let mut out = Vec::new();
    go(&[], tree, &mut out);
    out
}

fn load(src: &Path) -> BTreeMap<Vec<String>, Module> {
    let mut files = Vec::new();
    let mut stack = vec![src.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).expect("read src") {
            let path = entry.expect("dir entry").path();
            if path.is_dir() {
                if path.file_name().is_some_and(|n| n != "bin") {
                    stack.push(path);
                }
            } else if path.extension().is_some_and(|e| e == "rs") && path.file_name().is_some_and(|n| n != "main.rs") {
                files.push(path);
            }
        }
    }
    let mut test_files = BTreeSet::new();
    let mut modules = BTreeMap::new();
    for file in files {
        let rel = file.strip_prefix(src).expect("under src").with_extension("");
        let mut path: Vec<String> = rel.iter().map(|p| p.to_string_lossy().into_owned()).collect();
        let is_dir = matches!(path.last().map(String::as_str), Some("mod" | "lib"));
        if is_dir {
            path.pop();
        }
        let text = std::fs::read_to_string(&file).expect("read source");
        let (code, tests) = cut_tests(&strip(&text));
        for t in tests {
            let mut p = path.clone();
            if !is_dir {
                // `mod tests;` in a non-mod.rs file a.rs lives at a/tests.rs.
            }
            p.push(t);
            test_files.insert(p);
        }
        modules.insert(path, Module { file, code, is_dir, children: BTreeSet::new(), items: BTreeSet::new(), reexports: Vec::new(), paths: Vec::new() });
    }
    for t in &test_files {
        modules.remove(t);
    }
    let names: BTreeSet<Vec<String>> = modules.keys().cloned().collect();
    let item_re = regex::Regex::new(r"\b(?:struct|enum|trait|type|fn|const|static|union|macro_rules!)\s+([A-Za-z_]\w*)").unwrap();
    let use_re = regex::Regex::new(r"\b(pub(?:\s*\([^)]*\))?\s+)?use\s+([^;]+);").unwrap();
    let path_re = regex::Regex::new(r"\b(crate|super|self)((?:\s*::\s*[A-Za-z_]\w*)+)").unwrap();
    for (path, module) in modules.iter_mut() {
        module.children = names.iter().filter(|n| n.len() == path.len() + 1 && n.starts_with(path)).map(|n| n[path.len()].clone()).collect();
        module.items = item_re.captures_iter(&module.code).map(|c| c[1].to_string()).collect();
        let base_of = |first: &str| -> Option<Vec<String>> {
            match first {
                "crate" => Some(Vec::new()),
                "self" => Some(path.clone()),
                "super" => Some(path[..path.len().saturating_sub(1)].to_vec()),
                _ => None,
            }
        };
        let absolute = |p: &[String]| -> Option<Vec<String>> {
            let first = p.first()?;
            let mut abs = match base_of(first) {
                Some(b) => b,
                None if module.children.contains(first) => {
                    let mut b = path.clone();
                    b.push(first.clone());
                    return Some(b.into_iter().chain(p[1..].iter().cloned()).collect());
                }
                None => return None,
            };
            let mut rest = &p[1..];
            while rest.first().is_some_and(|s| s == "super") {
                abs.pop();
                rest = &rest[1..];
            }
            abs.extend(rest.iter().cloned());
            Some(abs)
        };
        let mut code_without_uses = module.code.clone();
        for c in use_re.captures_iter(&module.code) {
            let public = c.get(1).is_some_and(|p| !p.as_str().contains("super") && !p.as_str().contains("in "));
            for (p, name) in expand_use(&c[2]) {
                let Some(abs) = absolute(&p) else { continue };
                if public {
                    module.reexports.push((name, abs.clone()));
                }
                module.paths.push(abs);
            }
        }
        for c in use_re.find_iter(&module.code) {
            code_without_uses = code_without_uses.replacen(c.as_str(), "", 1);
        }
        for c in path_re.captures_iter(&code_without_uses) {
            let p: Vec<String> = std::iter::once(c[1].to_string()).chain(c[2].split("::").map(str::trim).filter(|s| !s.is_empty()).map(String::from)).collect();
            if let Some(abs) = absolute(&p) {
                module.paths.push(abs);
            }
        }
        let _ = module.is_dir;
    }
    modules
}

/// The module file that defines what `path` names, following re-exports.
fn resolve(modules: &BTreeMap<Vec<String>, Module>, path: &[String], depth: usize) -> Vec<String> {
    let mut cur: Vec<String> = Vec::new();
    for (i, seg) in path.iter().enumerate() {
        let Some(module) = modules.get(&cur) else { return cur };
        if module.children.contains(seg) {
            cur.push(seg.clone());
            continue;
        }
        if module.items.contains(seg) || depth > 8 {
            return cur;
        }
        if let Some((_, target)) = module.reexports.iter().find(|(name, _)| name == seg) {
            let mut full = target.clone();
            full.extend(path[i + 1..].iter().cloned());
            return resolve(modules, &full, depth + 1);
        }
        for (_, target) in module.reexports.iter().filter(|(name, _)| name == "*") {
            let glob = &target[..target.len() - 1];
            let mut full = glob.to_vec();
            full.extend(path[i..].iter().cloned());
            let found = resolve(modules, &full, depth + 1);
            if found != glob {
                return found;
            }
            if modules.get(glob).is_some_and(|m| m.items.contains(seg)) {
                return glob.to_vec();
            }
        }
        return cur;
    }
    cur
}

fn show(path: &[String]) -> String {
    if path.is_empty() {
        "lib".into()
    } else {
        path.join("::")
    }
}

type Edges = BTreeMap<Vec<String>, BTreeSet<Vec<String>>>;

fn graph() -> (BTreeMap<Vec<String>, Module>, Edges) {
    graph_of(&Path::new(env!("CARGO_MANIFEST_DIR")).join("src"))
}

fn graph_of(src: &Path) -> (BTreeMap<Vec<String>, Module>, Edges) {
    let modules = load(src);
    let mut edges = BTreeMap::new();
    for (path, module) in &modules {
        let mut to = BTreeSet::new();
        for p in &module.paths {
            let target = resolve(&modules, p, 0);
            if &target != path && modules.contains_key(&target) {
                to.insert(target);
            }
        }
        edges.insert(path.clone(), to);
    }
    (modules, edges)
}

fn floor_of(path: &[String], module: &Module) -> Option<&'static str> {
    if module.file.file_name().is_some_and(|n| n == "error.rs") {
        return Some("base");
    }
    floor_of_module(path.first()?)
}

#[test]
fn every_module_is_on_a_floor() {
    let (modules, _) = graph();
    let lost: Vec<String> =
        modules.iter().filter(|(p, m)| !p.is_empty() && floor_of(p, m).is_none()).map(|(p, _)| show(p)).collect();
    assert!(lost.is_empty(), "modules on no floor (add them to FLOORS' table and docs/architecture.md): {lost:?}");
}

/// The groups of files that import each other (through any chain).
fn cycles(edges: &Edges) -> Vec<Vec<String>> {
    // Tarjan's strongly connected components.
    struct State<'a> {
        edges: &'a BTreeMap<Vec<String>, BTreeSet<Vec<String>>>,
        index: BTreeMap<&'a [String], usize>,
        low: BTreeMap<&'a [String], usize>,
        stack: Vec<&'a [String]>,
        on: BTreeSet<&'a [String]>,
        cycles: Vec<Vec<String>>,
    }
    fn visit<'a>(s: &mut State<'a>, v: &'a [String]) {
        let i = s.index.len();
        s.index.insert(v, i);
        s.low.insert(v, i);
        s.stack.push(v);
        s.on.insert(v);
        for w in &s.edges[v] {
            let w = w.as_slice();
            if !s.index.contains_key(w) {
                visit(s, w);
                let lw = s.low[w];
                let lv = s.low.get_mut(v).unwrap();
                *lv = (*lv).min(lw);
            } else if s.on.contains(w) {
                let iw = s.index[w];
                let lv = s.low.get_mut(v).unwrap();
                *lv = (*lv).min(iw);
            }
        }
        if s.low[v] == s.index[v] {
            let mut component = Vec::new();
            loop {
                let w = s.stack.pop().unwrap();
                s.on.remove(w);
                component.push(show(w));
                if w == v {
                    break;
                }
            }
            if component.len() > 1 {
                component.sort();
                s.cycles.push(component);
            }
        }
    }
    let mut state = State { edges, index: BTreeMap::new(), low: BTreeMap::new(), stack: Vec::new(), on: BTreeSet::new(), cycles: Vec::new() };
    for v in edges.keys() {
        if !state.index.contains_key(v.as_slice()) {
            visit(&mut state, v);
        }
    }
    state.cycles
}

#[test]
fn no_import_cycle_between_files() {
    let (_, edges) = graph();
    let cycles = cycles(&edges);
    assert!(cycles.is_empty(), "files importing each other (through any chain): {cycles:?}");
}

/// Each import against the floors, as `from (floor) imports to (floor)`.
fn floor_violations(modules: &BTreeMap<Vec<String>, Module>, edges: &Edges) -> Vec<String> {
    let mut wrong = Vec::new();
    for (from, to) in edges {
        if from.is_empty() {
            continue; // lib.rs: the facade re-exports from every floor
        }
        let floor = floor_of(from, &modules[from]).unwrap_or("top");
        let allowed = FLOORS.iter().find(|(f, _)| *f == floor).map(|(_, a)| *a).unwrap_or(&[]);
        for target in to {
            if target.is_empty() || target.first() == from.first() {
                continue;
            }
            let target_floor = floor_of(target, &modules[target]).unwrap_or("top");
            if target_floor != floor && !allowed.contains(&target_floor) {
                wrong.push(format!("{} ({floor}) imports {} ({target_floor})", show(from), show(target)));
            }
        }
    }
    wrong
}

#[test]
fn imports_go_down_the_floors() {
    let (modules, edges) = graph();
    let wrong = floor_violations(&modules, &edges);
    assert!(wrong.is_empty(), "imports against the floors of docs/architecture.md:\n{}", wrong.join("\n"));
}

/// The `mod.rs` of these modules declares and re-exports only: what the children share is in
/// a file of its own, so no child imports its parent's re-exports.
const DECLARING_MODULES: &[&str] = &["operator"];

#[test]
fn declaring_mod_rs_files_hold_no_code() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut wrong = Vec::new();
    for module in DECLARING_MODULES {
        let text = std::fs::read_to_string(src.join(module).join("mod.rs")).expect("read mod.rs");
        let (code, _) = cut_tests(&strip(&text));
        let declaration = regex::Regex::new(r"^(pub(\([a-z]+\))?\s+)?(mod\s+\w+|use\s+[\w:]+(::\{[\w\s,:{}]*\})?)$").unwrap();
        for statement in code.split(';').map(str::trim).filter(|s| !s.is_empty()) {
            if !declaration.is_match(statement) {
                wrong.push(format!("src/{module}/mod.rs: {statement}"));
            }
        }
    }
    assert!(wrong.is_empty(), "code in a mod.rs that should only declare and re-export:\n{}", wrong.join("\n"));
}

/// Outside `stages/`, a stage module is reached only through the registry (`stages::builtin`)
/// and the typed parameters (`stages::params`, the facade's `params`): a kind's parameters are
/// defined in the kind's file, so the path as written must go through `params`.
#[test]
fn stage_modules_are_reached_only_through_the_registry() {
    let (modules, _) = graph();
    let through_params = |p: &[String]| p.first().is_some_and(|s| s == "params") || (p.len() > 1 && p[0] == "stages" && p[1] == "params");
    let mut wrong = Vec::new();
    for (from, module) in &modules {
        if from.first().map(String::as_str) == Some("stages") || from.is_empty() {
            continue;
        }
        for p in &module.paths {
            let target = resolve(&modules, p, 0);
            if target.first().map(String::as_str) == Some("stages") && target.len() > 1 && !through_params(p) {
                wrong.push(format!("{} imports {} ({})", show(from), show(&target), show(p)));
            }
        }
    }
    wrong.sort();
    wrong.dedup();
    assert!(wrong.is_empty(), "stage modules imported from outside stages/ (use the registry or stages::params, or move what they share below):\n{}", wrong.join("\n"));
}

/// What `check` makes of a small crate of `files` (path under `src/`, text), written for it.
fn in_crate<T>(name: &str, files: &[(&str, &str)], check: impl FnOnce(&Path) -> T) -> T {
    let dir = std::env::temp_dir().join(format!("r2d2-layering-{name}-{}", std::process::id()));
    for (file, text) in files {
        let path = dir.join(file);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, text).unwrap();
    }
    let result = check(&dir);
    std::fs::remove_dir_all(&dir).unwrap();
    result
}

#[test]
fn the_checker_sees_a_cycle_and_a_wrong_floor() {
    // A small crate with a cycle through a re-export (a mod.rs re-exporting a child that
    // imports what the mod.rs defines) and the pipeline importing the domain.
    let files = [
        ("lib.rs", "pub mod pipeline;\npub mod job;\n"),
        ("pipeline/mod.rs", "mod runner;\npub use runner::run;\n"),
        ("pipeline/runner.rs", "use crate::job::Job;\npub fn run(_: Job) {}\n"),
        ("job/mod.rs", "mod parts;\npub use parts::emit; // re-exported\npub struct Job;\n"),
        ("job/parts.rs", "/* use crate::pipeline::run; */\nuse super::Job;\npub fn emit(_: Job) { let _ = \"crate::pipeline::run\"; }\n#[cfg(test)]\nmod tests { use crate::pipeline::run; }\n"),
    ];
    let (modules, edges) = in_crate("graph", &files, graph_of);
    let job_parts = vec!["job".to_string(), "parts".to_string()];
    // Comments, strings and test modules are not imports.
    assert_eq!(edges[&job_parts], BTreeSet::from([vec!["job".to_string()]]));
    assert_eq!(cycles(&edges), vec![vec!["job".to_string(), "job::parts".to_string()]]);
    assert_eq!(floor_violations(&modules, &edges), vec!["pipeline::runner (pipeline) imports job (domain)".to_string()]);
    // Re-exports resolve to the defining file.
    assert_eq!(show(&resolve(&modules, &["pipeline".into(), "run".into()], 0)), "pipeline::runner");
    assert_eq!(expand_use("a::{b, c::{self, d as e}}").len(), 3);
}

/// The command line's long options of more than one word, without their dashes
/// (`freq-ratio`): each field under `#[arg(long)]` of the command-line modules (`cli`), spelled
/// with dashes, or the spelling `#[arg(long = "...")]` gives it.
fn command_line_options(modules: &BTreeMap<Vec<String>, Module>) -> BTreeSet<String> {
    let long = regex::Regex::new(r"\blong\b").unwrap();
    let spelled = regex::Regex::new(r#"\blong\s*=\s*"([^"]+)""#).unwrap();
    let field = regex::Regex::new(r"^\s*(?:pub(?:\([^)]*\))?\s+)?([a-z_][a-z0-9_]*)\s*:").unwrap();
    let mut options = BTreeSet::new();
    for module in modules.iter().filter(|(p, _)| p.first().is_some_and(|t| t == "cli")).map(|(_, m)| m) {
        let text = std::fs::read_to_string(&module.file).expect("read source");
        let mut unnamed = false;
        for line in text.lines() {
            let trimmed = line.trim_start();
            if trimmed.starts_with("#[arg(") || trimmed.starts_with("#[clap(") {
                match spelled.captures(trimmed) {
                    Some(c) => options.insert(c[1].to_string()),
                    None => {
                        unnamed = long.is_match(trimmed);
                        continue;
                    }
                };
            } else if unnamed && !trimmed.starts_with("#[") && !trimmed.starts_with("//") {
                if let Some(c) = field.captures(line) {
                    options.insert(c[1].replace('_', "-"));
                }
                unnamed = false;
            }
        }
    }
    options.retain(|o| o.contains('-'));
    options
}

/// Options of commands spelled as the command line spells them (`--auto-threshold`) in the
/// string literals of a module below the top floor, or a whole literal that is a long option
/// of several words without its dashes (`"freq-ratio"`, an error's parameter name): the
/// library names the request's fields (`auto_threshold`) and each interface (CLI, YAML,
/// Python) adds its own spelling. Cargo's own options are not this program's.
fn command_line_spellings(modules: &BTreeMap<Vec<String>, Module>) -> Vec<String> {
    const NOT_OURS: &[&str] = &["--release"];
    let options = command_line_options(modules);
    let mut found = Vec::new();
    for (path, module) in modules {
        if path.is_empty() || floor_of(path, module).is_none_or(|f| f == "top") || module.file.file_name().is_some_and(|n| n == "tests.rs") {
            continue;
        }
        let text = std::fs::read_to_string(&module.file).expect("read source");
        // The test module closes the file (its strings may name options: they test the CLI).
        let code = text.find("#[cfg(test)]\nmod tests").map_or(text.as_str(), |at| &text[..at]);
        for (number, line) in code.lines().enumerate() {
            let trimmed = line.trim_start();
            if trimmed.starts_with("//") {
                continue;
            }
            // The line's string literals (a string broken over lines is read line by line).
            for (k, literal) in line.split('"').enumerate() {
                if k % 2 == 0 {
                    continue;
                }
                if options.contains(literal) {
                    found.push(format!("{}:{}: \"{literal}\" (--{literal})", module.file.display(), number + 1));
                }
                let bytes = literal.as_bytes();
                for at in literal.match_indices("--").map(|(i, _)| i) {
                    let before = at.checked_sub(1).map(|i| bytes[i]);
                    let first = bytes.get(at + 2).copied();
                    if before.is_some_and(|b| b == b'-' || b.is_ascii_alphanumeric()) || !first.is_some_and(|b| b.is_ascii_lowercase()) {
                        continue;
                    }
                    let word: String = literal[at..].chars().take_while(|c| *c == '-' || c.is_ascii_alphanumeric()).collect();
                    if !NOT_OURS.contains(&word.as_str()) {
                        found.push(format!("{}:{}: {word}", module.file.display(), number + 1));
                    }
                }
            }
        }
    }
    found
}

#[test]
fn no_command_line_spelling_below_the_top_floor() {
    let (modules, _) = graph();
    let found = command_line_spellings(&modules);
    assert!(found.is_empty(), "command-line options named below the top floor (name the request's field instead): {found:#?}");
}

#[test]
fn the_checker_sees_an_option_named_below_the_top_floor() {
    // A command with options of one and of several words, one spelled by `long = "..."`, and a
    // library module naming one by its field, two by the command line's spelling.
    let files = [
        ("cli/mod.rs", "#[derive(clap::Args)]\npub struct Args {\n    /// Ratio.\n    #[arg(long)]\n    freq_ratio: f64,\n    #[arg(long = \"flag-fraction\", default_value_t = 0.0)]\n    flag: f64,\n    #[arg(long)]\n    seed: u64,\n    #[arg(long_help = \"x\")]\n    no_long: bool,\n}\n"),
        ("simulate/observe.rs", "fn f() -> Error {\n    check(1.0, \"freq-ratio\");\n    let _ = (\"field-filling\", \"seed\", \"no-long\", \"flag_fraction\");\n    Error::parameter(\n        \"flag-fraction\",\n        \"expected a fraction\",\n    )\n}\n"),
    ];
    let (options, found) = in_crate("options", &files, |src| {
        let (modules, _) = graph_of(src);
        (command_line_options(&modules), command_line_spellings(&modules))
    });
    assert_eq!(options, BTreeSet::from(["flag-fraction".to_string(), "freq-ratio".to_string()]));
    let found: Vec<&str> = found.iter().map(|f| f.split_once(": ").map_or(f.as_str(), |(_, w)| w)).collect();
    assert_eq!(found, ["\"freq-ratio\" (--freq-ratio)", "\"flag-fraction\" (--flag-fraction)"]);
}
