//! The code's layout: no import cycle between the files of any crate of the workspace.
//!
//! Each crate's module tree is followed from its roots (`lib.rs`, `main.rs`, or the `path`s its
//! `Cargo.toml` names) through `mod NAME;` declarations. In every file, each path that starts at
//! `crate::`, `super::`, `self::` or at a child module of the module it is written in (`use`
//! trees included) is resolved to the file of its longest module prefix, through the `use`
//! bindings of the modules on the way (so `crate::Context`, re-exported by `lib.rs`, is
//! `context.rs`'s); that is an edge from the file to that one. A `pub use` re-export makes no
//! edge of its own: a parent module that re-exports a child's item does not depend on it. Inline modules (`mod tests { .. }`) belong to their file. A cycle of
//! edges between files fails the test with the paths that make it.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// A module's path from its crate root.
type ModPath = Vec<String>;
/// A `use` binding: the module it is made in and the name it binds.
type Binding = (ModPath, String);
/// A file's tokens with their lines.
type Tokens = Vec<(Tok, usize)>;

/// A token of Rust source, as far as paths need: identifiers and the punctuation around them.
#[derive(Clone, Debug, PartialEq)]
enum Tok {
    Ident(String),
    PathSep,
    Open,
    Close,
    Comma,
    Semi,
    Star,
    OpenParen,
    CloseParen,
    Other,
}

/// Tokens of `src` with their line numbers, without comments, strings and character literals.
fn lex(src: &str) -> Vec<(Tok, usize)> {
    let c: Vec<char> = src.chars().collect();
    let mut out = Vec::new();
    let (mut i, mut line) = (0, 1);
    let at = |i: usize| c.get(i).copied().unwrap_or('\0');
    while i < c.len() {
        let ch = c[i];
        if ch == '\n' {
            line += 1;
            i += 1;
        } else if ch.is_whitespace() {
            i += 1;
        } else if ch == '/' && at(i + 1) == '/' {
            while i < c.len() && c[i] != '\n' {
                i += 1;
            }
        } else if ch == '/' && at(i + 1) == '*' {
            let mut depth = 0;
            while i < c.len() {
                if c[i] == '/' && at(i + 1) == '*' {
                    depth += 1;
                    i += 2;
                } else if c[i] == '*' && at(i + 1) == '/' {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    line += usize::from(c[i] == '\n');
                    i += 1;
                }
            }
        } else if ch == '"' || ((ch == 'b' || ch == 'c') && at(i + 1) == '"') {
            i += if ch == '"' { 1 } else { 2 };
            while i < c.len() && c[i] != '"' {
                if c[i] == '\\' {
                    i += 1;
                }
                line += usize::from(at(i) == '\n');
                i += 1;
            }
            i += 1;
        } else if (ch == 'r' || (ch == 'b' && at(i + 1) == 'r'))
            && matches!(at(i + if ch == 'r' { 1 } else { 2 }), '"' | '#')
            && {
                // A raw string: r"..", r#".."#, br"..".
                let mut j = i + if ch == 'r' { 1 } else { 2 };
                while at(j) == '#' {
                    j += 1;
                }
                at(j) == '"'
            }
        {
            let mut j = i + if ch == 'r' { 1 } else { 2 };
            let mut hashes = 0;
            while at(j) == '#' {
                hashes += 1;
                j += 1;
            }
            j += 1;
            loop {
                if j >= c.len() {
                    break;
                }
                if c[j] == '"' && (1..=hashes).all(|k| at(j + k) == '#') {
                    j += 1 + hashes;
                    break;
                }
                line += usize::from(c[j] == '\n');
                j += 1;
            }
            i = j;
        } else if ch == '\'' {
            // A character literal ('x', '\n', '\u{..}') or a lifetime ('a).
            if at(i + 1) == '\\' {
                i += 2;
                while i < c.len() && c[i] != '\'' {
                    i += 1;
                }
                i += 1;
            } else if at(i + 2) == '\'' {
                i += 3;
            } else {
                i += 1;
                while at(i).is_alphanumeric() || at(i) == '_' {
                    i += 1;
                }
            }
        } else if ch.is_alphabetic() || ch == '_' {
            let s = i;
            while at(i).is_alphanumeric() || at(i) == '_' {
                i += 1;
            }
            let word: String = c[s..i].iter().collect();
            // A raw identifier r#name is the identifier.
            if word == "r" && at(i) == '#' && at(i + 1).is_alphabetic() {
                continue;
            }
            out.push((Tok::Ident(word), line));
        } else if ch.is_ascii_digit() {
            while at(i).is_alphanumeric() || at(i) == '_' || at(i) == '.' && at(i + 1) != '.' {
                i += 1;
            }
            out.push((Tok::Other, line));
        } else {
            let t = match ch {
                ':' if at(i + 1) == ':' => {
                    i += 1;
                    Tok::PathSep
                }
                '{' => Tok::Open,
                '}' => Tok::Close,
                ',' => Tok::Comma,
                ';' => Tok::Semi,
                '*' => Tok::Star,
                '(' => Tok::OpenParen,
                ')' => Tok::CloseParen,
                _ => Tok::Other,
            };
            i += 1;
            out.push((t, line));
        }
    }
    out
}

/// One file's module declarations (`mod NAME;`, with the module path they are declared in)
/// and the absolute paths it names (with their lines).
#[derive(Debug, Default)]
struct FileScan {
    children: Vec<(Vec<String>, String)>,
    paths: Vec<PathRef>,
    /// `use` bindings: (module, name) -> the path it names (globs left out).
    imports: Vec<(Binding, ModPath)>,
}

/// A path named in a file, at a line.
#[derive(Clone, Debug)]
struct PathRef {
    path: Vec<String>,
    line: usize,
    /// In a `use` tree: the name it binds (None for a glob).
    bind: Option<String>,
    /// In a `pub use`: a re-export, which makes no edge of its own (paths through it resolve
    /// to the file that defines the item).
    reexport: bool,
}

/// Scans a file of module `module`: inline modules extend the module path inside their braces;
/// `children` of the file's modules are path roots too (so the scan runs after the file's
/// `mod` declarations are known: two passes).
fn scan(toks: &[(Tok, usize)], module: &[String], declared: &BTreeSet<Vec<String>>) -> FileScan {
    let mut f = FileScan::default();
    // The module path at each brace depth where an inline module opened.
    let mut stack: Vec<(usize, Vec<String>)> = vec![(0, module.to_vec())];
    let mut depth = 0usize;
    let mut i = 0;
    let ident = |k: usize| match toks.get(k) {
        Some((Tok::Ident(s), _)) => Some(s.as_str()),
        _ => None,
    };
    let (mut in_use, mut reexport) = (false, false);
    while i < toks.len() {
        let here = stack.last().map(|s| s.1.clone()).unwrap_or_default();
        match &toks[i].0 {
            Tok::Semi => in_use = false,
            Tok::Ident(w) if w == "use" => {
                in_use = true;
                // `pub use` or `pub(crate) use`.
                let tok = |k: usize| toks.get(k).map(|t| &t.0);
                reexport = ident(i.wrapping_sub(1)) == Some("pub")
                    || (i >= 4
                        && ident(i - 4) == Some("pub")
                        && tok(i - 3) == Some(&Tok::OpenParen)
                        && tok(i - 1) == Some(&Tok::CloseParen));
            }
            _ => {}
        }
        match &toks[i].0 {
            Tok::Open => {
                depth += 1;
                i += 1;
                continue;
            }
            Tok::Close => {
                if stack.len() > 1 && stack.last().is_some_and(|s| s.0 == depth) {
                    stack.pop();
                }
                depth = depth.saturating_sub(1);
                i += 1;
                continue;
            }
            _ => {}
        }
        if ident(i) == Some("mod") {
            if let Some(name) = ident(i + 1) {
                match toks.get(i + 2).map(|t| &t.0) {
                    Some(Tok::Semi) => f.children.push((here.clone(), name.to_string())),
                    Some(Tok::Open) => {
                        let mut m = here.clone();
                        m.push(name.to_string());
                        depth += 1;
                        stack.push((depth, m));
                        i += 3;
                        continue;
                    }
                    _ => {}
                }
                i += 2;
                continue;
            }
        }
        // A path starts here unless it continues one (`a::b`) or is a field or method (`x.b`).
        let prev = i.checked_sub(1).map(|k| &toks[k].0);
        if let (Some(word), false) = (ident(i), matches!(prev, Some(Tok::PathSep))) {
            let line = toks[i].1;
            // The module the path starts at, and the index of the `::` after that start.
            let start: Option<(Vec<String>, usize)> = match word {
                "crate" | "self" | "super"
                    if toks.get(i + 1).map(|t| &t.0) != Some(&Tok::PathSep) =>
                {
                    None
                }
                "crate" => Some((Vec::new(), i + 1)),
                "self" => Some((here.clone(), i + 1)),
                "super" => {
                    let mut m = here.clone();
                    let mut k = i;
                    m.pop();
                    while toks.get(k + 1).map(|t| &t.0) == Some(&Tok::PathSep)
                        && ident(k + 2) == Some("super")
                    {
                        m.pop();
                        k += 2;
                    }
                    Some((m, k + 1))
                }
                w => {
                    let mut m = here.clone();
                    m.push(w.to_string());
                    (declared.contains(&m) && toks.get(i + 1).map(|t| &t.0) == Some(&Tok::PathSep))
                        .then_some((m, i + 1))
                }
            };
            if let Some((prefix, next)) = start {
                let first = f.paths.len();
                i = tree(toks, next, prefix, line, &mut f.paths);
                for r in &mut f.paths[first..] {
                    r.reexport = in_use && reexport;
                    if !in_use {
                        r.bind = None;
                    } else if let Some(b) = &r.bind {
                        f.imports.push(((here.clone(), b.clone()), r.path.clone()));
                    }
                }
                continue;
            }
        }
        i += 1;
    }
    f
}

/// Reads a path (or a `use` tree) whose segments so far are `prefix`, from `toks[i]` (the
/// token after the last segment read); pushes every full path; returns the index after it.
fn tree(
    toks: &[(Tok, usize)],
    mut i: usize,
    mut prefix: Vec<String>,
    line: usize,
    out: &mut Vec<PathRef>,
) -> usize {
    loop {
        if toks.get(i).map(|t| &t.0) != Some(&Tok::PathSep) {
            // `a::b as c` binds c.
            let alias = match (toks.get(i).map(|t| &t.0), toks.get(i + 1).map(|t| &t.0)) {
                (Some(Tok::Ident(a)), Some(Tok::Ident(c))) if a == "as" => Some(c.clone()),
                _ => None,
            };
            let bind = alias.or_else(|| prefix.last().cloned());
            out.push(PathRef {
                path: prefix,
                line,
                bind,
                reexport: false,
            });
            return i;
        }
        match toks.get(i + 1).map(|t| &t.0) {
            Some(Tok::Ident(s)) => {
                prefix.push(s.clone());
                i += 2;
            }
            Some(Tok::Open) => return group(toks, i + 1, &prefix, line, out),
            _ => {
                // `a::*` (a glob) or `a::<T>`.
                out.push(PathRef {
                    path: prefix,
                    line,
                    bind: None,
                    reexport: false,
                });
                return i + 2;
            }
        }
    }
}

/// Reads a `use` group `{a, b::c, self, d as e, *, {f}}` under `prefix` from its `{` at
/// `toks[i]`; returns the index after its `}`.
fn group(
    toks: &[(Tok, usize)],
    mut i: usize,
    prefix: &[String],
    line: usize,
    out: &mut Vec<PathRef>,
) -> usize {
    i += 1;
    loop {
        match toks.get(i).map(|t| &t.0) {
            Some(Tok::Close) | None => return i + 1,
            Some(Tok::Open) => i = group(toks, i, prefix, line, out),
            Some(Tok::Ident(s)) if s == "self" => {
                i = tree(toks, i + 1, prefix.to_vec(), line, out);
            }
            Some(Tok::Ident(s)) if s == "as" => i += 2,
            Some(Tok::Ident(s)) => {
                let mut p = prefix.to_vec();
                p.push(s.clone());
                i = tree(toks, i + 1, p, line, out);
            }
            Some(Tok::Star) => {
                out.push(PathRef {
                    path: prefix.to_vec(),
                    line,
                    bind: None,
                    reexport: false,
                });
                i += 1;
            }
            _ => i += 1,
        }
    }
}

/// The file of module `name` declared in module file `parent` (`lib.rs`, `main.rs`, `mod.rs` or
/// a crate root own their folder; `a.rs` owns `a/`).
fn child_file(
    parent: &Path,
    is_root: bool,
    name: &str,
    exists: &dyn Fn(&Path) -> bool,
) -> Option<PathBuf> {
    let dir = parent.parent()?;
    let stem = parent.file_stem()?.to_str()?;
    let base = if is_root || stem == "mod" || stem == "lib" || stem == "main" {
        dir.to_path_buf()
    } else {
        dir.join(stem)
    };
    [
        base.join(format!("{name}.rs")),
        base.join(name).join("mod.rs"),
    ]
    .into_iter()
    .find(|p| exists(p))
}

/// A crate's files and the edges between them: `(from, to) -> (line in from, path)`.
struct Graph {
    edges: BTreeMap<(PathBuf, PathBuf), (usize, String)>,
    files: usize,
}

/// The file graph of the crate rooted at `roots` (each its own module tree).
fn crate_graph(
    roots: &[PathBuf],
    read: &dyn Fn(&Path) -> Option<String>,
    exists: &dyn Fn(&Path) -> bool,
) -> Graph {
    let mut edges = BTreeMap::new();
    let mut files = 0;
    for root in roots {
        // Module path -> file, and each file's tokens, following `mod` declarations.
        let mut modules: BTreeMap<Vec<String>, PathBuf> = BTreeMap::new();
        let mut toks: BTreeMap<PathBuf, (ModPath, Tokens)> = BTreeMap::new();
        let mut todo = vec![(Vec::<String>::new(), root.clone())];
        while let Some((m, file)) = todo.pop() {
            let Some(src) = read(&file) else { continue };
            let t = lex(&src);
            let s = scan(&t, &m, &BTreeSet::new());
            modules.insert(m.clone(), file.clone());
            for (within, name) in s.children {
                let mut cm = within.clone();
                cm.push(name.clone());
                // A child of an inline module lives in that module's folder; not used here.
                if within != m {
                    continue;
                }
                if let Some(p) = child_file(&file, file == *root, &name, exists) {
                    todo.push((cm, p));
                }
            }
            toks.insert(file, (m, t));
        }
        let declared: BTreeSet<Vec<String>> = modules.keys().cloned().collect();
        files += toks.len();
        let scans: Vec<(&PathBuf, FileScan)> = toks
            .iter()
            .map(|(file, (m, t))| (file, scan(t, m, &declared)))
            .collect();
        let imports: BTreeMap<Binding, ModPath> = scans
            .iter()
            .flat_map(|(_, s)| s.imports.iter().cloned())
            .collect();
        for (file, s) in &scans {
            for r in s.paths.iter().filter(|r| !r.reexport) {
                let Some(to) = resolve(&r.path, &modules, &imports) else {
                    continue;
                };
                if to != **file {
                    edges
                        .entry(((*file).clone(), to))
                        .or_insert((r.line, format!("crate::{}", r.path.join("::"))));
                }
            }
        }
    }
    Graph { edges, files }
}

/// The file that defines what `path` (absolute) names: the file of its longest module prefix,
/// through the `use` bindings (re-exports included) of the modules on the way.
fn resolve(
    path: &[String],
    modules: &BTreeMap<Vec<String>, PathBuf>,
    imports: &BTreeMap<Binding, ModPath>,
) -> Option<PathBuf> {
    let mut p = path.to_vec();
    for _ in 0..16 {
        let k = (0..=p.len())
            .rev()
            .find(|&k| modules.contains_key(&p[..k]))?;
        let next = p
            .get(k)
            .and_then(|name| imports.get(&(p[..k].to_vec(), name.clone())));
        match next {
            Some(t) if t[..] != p[..=k] => {
                let mut q = t.clone();
                q.extend_from_slice(&p[k + 1..]);
                p = q;
            }
            _ => return modules.get(&p[..k]).cloned(),
        }
    }
    None
}

/// The cycles of `g` (its strongly connected components of more than one file), each as the
/// edges inside it.
fn cycles(g: &Graph) -> Vec<Vec<String>> {
    let nodes: BTreeSet<&PathBuf> = g.edges.keys().flat_map(|(a, b)| [a, b]).collect();
    let reach = |from: &PathBuf| -> BTreeSet<PathBuf> {
        let mut seen = BTreeSet::new();
        let mut todo = vec![from.clone()];
        while let Some(n) = todo.pop() {
            for (a, b) in g.edges.keys() {
                if *a == n && seen.insert(b.clone()) {
                    todo.push(b.clone());
                }
            }
        }
        seen
    };
    let reaches: BTreeMap<&PathBuf, BTreeSet<PathBuf>> =
        nodes.iter().map(|n| (*n, reach(n))).collect();
    let mut done = BTreeSet::new();
    let mut out = Vec::new();
    for n in &nodes {
        if done.contains(*n) || !reaches[n].contains(*n) {
            continue;
        }
        let comp: BTreeSet<&PathBuf> = nodes
            .iter()
            .copied()
            .filter(|m| reaches[n].contains(*m) && reaches[m].contains(*n))
            .collect();
        let lines = g
            .edges
            .iter()
            .filter(|((a, b), _)| comp.contains(a) && comp.contains(b))
            .map(|((a, b), (line, p))| format!("{}:{line} -> {} ({p})", a.display(), b.display()))
            .collect();
        done.extend(comp.into_iter().cloned());
        out.push(lines);
    }
    out
}

/// The workspace's crates: each member folder with its root files.
fn workspace_roots(ws: &Path) -> Vec<(PathBuf, Vec<PathBuf>)> {
    let manifest = std::fs::read_to_string(ws.join("Cargo.toml")).expect("reading Cargo.toml");
    let members_line = manifest
        .lines()
        .find(|l| l.trim_start().starts_with("members"))
        .expect("Cargo.toml has no members line");
    let members: Vec<&str> = members_line.split('"').skip(1).step_by(2).collect();
    assert!(
        !members.is_empty(),
        "no workspace members in {members_line}"
    );
    members
        .into_iter()
        .map(|m| {
            let dir = ws.join(m);
            let cargo = std::fs::read_to_string(dir.join("Cargo.toml"))
                .unwrap_or_else(|e| panic!("reading {}/Cargo.toml: {e}", dir.display()));
            let mut roots: BTreeSet<PathBuf> = cargo
                .lines()
                .filter_map(|l| {
                    let l = l.trim();
                    let rest = l.strip_prefix("path")?.trim_start().strip_prefix('=')?;
                    let p = rest.trim().trim_matches('"');
                    p.ends_with(".rs").then(|| dir.join(p))
                })
                .collect();
            for d in ["src/lib.rs", "src/main.rs"] {
                if dir.join(d).exists() {
                    roots.insert(dir.join(d));
                }
            }
            (dir, roots.into_iter().collect())
        })
        .collect()
}

#[test]
fn no_file_of_any_crate_imports_one_that_imports_it_back() {
    let ws = Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the tests crate sits in the workspace")
        .to_path_buf();
    let mut found = Vec::new();
    let mut files = 0;
    for (dir, roots) in workspace_roots(&ws) {
        assert!(!roots.is_empty(), "{}: no crate root", dir.display());
        let g = crate_graph(&roots, &|p| std::fs::read_to_string(p).ok(), &|p| {
            p.exists()
        });
        files += g.files;
        for c in cycles(&g) {
            found.push(c.join("\n  "));
        }
    }
    // The walk saw the workspace (a broken walk would find no cycle in nothing).
    assert!(
        files > 100,
        "only {files} files found under {}",
        ws.display()
    );
    assert!(
        found.is_empty(),
        "import cycles between files:\n  {}",
        found.join("\n\n  ")
    );
}

/// A crate in memory: file -> text.
fn graph_of(files: &[(&str, &str)]) -> Graph {
    let m: BTreeMap<PathBuf, String> = files
        .iter()
        .map(|(p, s)| (PathBuf::from(p), s.to_string()))
        .collect();
    crate_graph(
        &[PathBuf::from("src/lib.rs")],
        &|p| m.get(p).cloned(),
        &|p| m.contains_key(p),
    )
}

fn edge_set(g: &Graph) -> BTreeSet<(String, String)> {
    g.edges
        .keys()
        .map(|(a, b)| (a.display().to_string(), b.display().to_string()))
        .collect()
}

#[test]
fn the_layout_check_finds_the_edges_of_every_kind_of_path() {
    let g = graph_of(&[
        ("src/lib.rs", "pub mod a;\npub mod b;\nmod c;\npub use c::C;\n"),
        (
            "src/a.rs",
            "mod inner;\nuse crate::{b::{self, B}, c::*};\nfn f() { inner::go(); let s = \"crate::d::X {\"; }\n",
        ),
        ("src/a/inner.rs", "pub fn go() { super::super::b::B::new(); }\n"),
        (
            "src/b.rs",
            "// crate::a::A in a comment\npub struct B;\nfn h() { let _ = crate::C; }\n#[cfg(test)]\nmod tests {\n    use super::*;\n    fn t() { let _c = '{'; }\n}\nfn g<'a>(x: &'a str) {}\n",
        ),
        ("src/c/mod.rs", "pub struct C;\nfn f() { self::d::D; }\nmod d;\n"),
        ("src/c/d.rs", "pub struct D;\nfn f() { r#\"crate::a\"#; }\n"),
    ]);
    assert_eq!(g.files, 6);
    let want: BTreeSet<(String, String)> = [
        // lib.rs's `pub use c::C` is no edge; b.rs's `crate::C` resolves through it.
        ("src/b.rs", "src/c/mod.rs"),
        ("src/a.rs", "src/b.rs"),
        ("src/a.rs", "src/c/mod.rs"),
        ("src/a.rs", "src/a/inner.rs"),
        ("src/a/inner.rs", "src/b.rs"),
        ("src/c/mod.rs", "src/c/d.rs"),
    ]
    .iter()
    .map(|(a, b)| (a.to_string(), b.to_string()))
    .collect();
    assert_eq!(edge_set(&g), want);
    assert!(cycles(&g).is_empty());
}

#[test]
fn the_layout_check_reports_a_cycle_through_three_files_and_only_it() {
    let g = graph_of(&[
        ("src/lib.rs", "mod a;\nmod b;\nmod c;\nmod d;\n"),
        ("src/a.rs", "use crate::b::B;\n"),
        ("src/b.rs", "pub struct B;\nfn f() { crate::c::C; }\n"),
        ("src/c.rs", "pub struct C;\nuse super::a;\n"),
        ("src/d.rs", "use crate::a;\n"),
    ]);
    let c = cycles(&g);
    assert_eq!(c.len(), 1, "{c:?}");
    assert_eq!(c[0].len(), 3, "{c:?}");
    assert!(c[0][0].starts_with("src/a.rs:1 -> src/b.rs"), "{c:?}");
    assert!(c[0].iter().all(|l| !l.contains("src/d.rs")), "{c:?}");
}

/// Each function of `toks` (with a body): its name, first line and length in lines.
fn functions(toks: &[(Tok, usize)]) -> Vec<(String, usize, usize)> {
    let mut out = Vec::new();
    for (i, (t, line)) in toks.iter().enumerate() {
        let (Tok::Ident(f), Some((Tok::Ident(name), _))) = (t, toks.get(i + 1)) else {
            continue;
        };
        if f != "fn" {
            continue;
        }
        // The body's `{`, unless a `;` ends a declaration first (outside parentheses).
        let mut parens = 0i32;
        let mut k = i + 2;
        let open = loop {
            match toks.get(k).map(|t| &t.0) {
                None | Some(Tok::Semi) if parens == 0 => break None,
                None => break None,
                Some(Tok::OpenParen) => parens += 1,
                Some(Tok::CloseParen) => parens -= 1,
                Some(Tok::Open) if parens == 0 => break Some(k),
                _ => {}
            }
            k += 1;
        };
        let Some(open) = open else { continue };
        let mut depth = 0;
        for (t, end) in &toks[open..] {
            match t {
                Tok::Open => depth += 1,
                Tok::Close => {
                    depth -= 1;
                    if depth == 0 {
                        out.push((name.clone(), *line, end - line + 1));
                        break;
                    }
                }
                _ => {}
            }
        }
    }
    out
}

/// The `.rs` files under `dir`.
fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        let entries = std::fs::read_dir(&d).unwrap_or_else(|e| panic!("{}: {e}", d.display()));
        for e in entries {
            let p = e.expect("a folder entry").path();
            if p.is_dir() {
                todo.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

#[test]
fn the_extranerf_crate_and_the_training_driver_keep_files_and_functions_short() {
    let ws = Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the tests crate sits in the workspace")
        .to_path_buf();
    let mut long = Vec::new();
    let mut seen = 0;
    for dir in ["engine/extrapolate/src", "engine/nerf/src/train"] {
        for p in rust_files(&ws.join(dir)) {
            let src = std::fs::read_to_string(&p).expect("reading a source file");
            let lines = src.lines().count();
            if lines > 800 {
                long.push(format!("{}: {lines} lines (at most 800)", p.display()));
            }
            for (name, line, n) in functions(&lex(&src)) {
                seen += 1;
                if n > 150 {
                    long.push(format!(
                        "{}:{line}: fn {name} is {n} lines (at most 150)",
                        p.display()
                    ));
                }
            }
        }
    }
    assert!(seen > 200, "only {seen} functions found");
    assert!(long.is_empty(), "{}", long.join("\n"));
}

#[test]
fn function_lengths_count_bodies_and_skip_declarations() {
    let src = "trait T {\n    fn decl(&self) -> u32;\n}\nfn one() {}\nfn three(f: fn(u32) -> u32) -> Vec<u32> {\n    let s = \"}\";\n    vec![f(1)]\n}\n";
    let f = functions(&lex(src));
    assert_eq!(f, vec![("one".into(), 4, 1), ("three".into(), 5, 4)]);
}

/// Every output a user keeps goes through the one atomic-write helper
/// (`extranerf_gpu::files::write_atomic`, or `write_atomic_with` for a streamed one): no
/// library or command-line source writes a file in place. Allowed: the helper itself, and
/// the video writer's `.partial` file (streamed, synced and renamed when whole). Test modules
/// (from a file's `#[cfg(test)]` on) are left out; append-only logs open with `OpenOptions`.
#[test]
fn outputs_go_through_the_atomic_write_helper() {
    let ws = Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the tests crate sits in the workspace")
        .to_path_buf();
    let allowed = ["engine/gpu/src/files.rs", "engine/nerf/src/video.rs"];
    let mut in_place = Vec::new();
    let mut files = 0;
    for dir in ["engine", "bin/src"] {
        for p in rust_files(&ws.join(dir)) {
            let rel = p
                .strip_prefix(&ws)
                .unwrap()
                .to_string_lossy()
                .replace('\\', "/");
            if !(rel.starts_with("bin/src") || rel.contains("/src/"))
                || allowed.contains(&rel.as_str())
            {
                continue;
            }
            files += 1;
            let src = std::fs::read_to_string(&p).expect("reading a source file");
            let body = src.split("#[cfg(test)]").next().unwrap_or("");
            for (k, line) in body.lines().enumerate() {
                let code = line.split("//").next().unwrap_or("");
                for pat in ["fs::write(", "File::create(", "fs::rename(", "fs::copy("] {
                    if code.contains(pat) {
                        in_place.push(format!("{rel}:{}: {}", k + 1, line.trim()));
                    }
                }
            }
        }
    }
    assert!(files > 100, "only {files} source files found");
    assert!(
        in_place.is_empty(),
        "written in place:\n{}",
        in_place.join("\n")
    );
}
