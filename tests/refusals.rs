//! docs/refusals.md names, for every refusal, the test that covers it: each named test must exist,
//! so that the table cannot outlive a renamed or removed test.

use std::path::Path;

/// `path::name` references in the table's last column.
fn referenced_tests(table: &str) -> Vec<(String, String)> {
    table
        .lines()
        .filter(|line| line.starts_with('|'))
        .filter_map(|line| line.trim_end_matches('|').rsplit('|').next())
        .filter_map(|cell| cell.trim().strip_prefix('`')?.strip_suffix('`').map(str::to_owned))
        .filter_map(|reference| {
            let (path, name) = reference.split_once("::")?;
            Some((path.to_owned(), name.to_owned()))
        })
        .collect()
}

#[test]
fn every_refusal_in_the_table_names_a_test_that_exists() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let table = std::fs::read_to_string(root.join("docs/refusals.md")).unwrap();
    let references = referenced_tests(&table);
    assert!(references.len() >= 20, "only {} refusals are listed", references.len());
    for (path, name) in references {
        let source = std::fs::read_to_string(root.join(&path)).unwrap_or_else(|e| panic!("{path}: {e}"));
        let definition = if path.ends_with(".py") {
            format!("def {name}(")
        } else {
            format!("fn {name}(")
        };
        assert!(
            source.contains(&definition),
            "docs/refusals.md names {path}::{name}, which does not exist"
        );
    }
}
