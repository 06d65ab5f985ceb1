//! polars lives in `pipe-report`, which only the `pipe` binary links (ARCHITECTURE §2): this
//! test binary, built from the library, must not contain it.

/// Whether the file at `path` contains `needle`.
fn contains(path: &std::path::Path, needle: &[u8]) -> bool {
    let bytes = std::fs::read(path).unwrap();
    bytes.windows(needle.len()).any(|w| w == needle)
}

/// `text` with every byte shifted up by one, so that this binary does not hold the needle
/// itself as a literal.
fn unshift(text: &[u8]) -> Vec<u8> {
    text.iter().map(|b| b - 1).collect()
}

#[test]
fn polars_is_in_the_binary_and_not_in_the_library_tests() {
    let me = std::env::current_exe().unwrap();
    // `polars_core` (symbols) and `polars-core` (source paths of panic locations).
    let needles = [unshift(b"qpmbst`dpsf"), unshift(b"qpmbst.dpsf")];
    for needle in &needles {
        assert!(
            !contains(&me, needle),
            "{} links polars (`{}` found)",
            me.display(),
            String::from_utf8_lossy(needle)
        );
    }
    // The search finds it where it is.
    let bin = std::path::Path::new(env!("CARGO_BIN_EXE_pipe"));
    assert!(contains(bin, &needles[0]), "{}", bin.display());
}
