//! `replay TARGET FILE...`: runs a fuzz target once on each file, outside AFL — to reproduce a
//! finding, or to check a corpus after a change. Exits non-zero on the first panic.
fn main() {
    let mut args = std::env::args().skip(1);
    let target = args.next().unwrap_or_default();
    let files: Vec<String> = args.collect();
    if !splatmark_fuzz::TARGETS.contains(&target.as_str()) || files.is_empty() {
        eprintln!(
            "usage: replay TARGET FILE...  (TARGET one of {})",
            splatmark_fuzz::TARGETS.join(", ")
        );
        std::process::exit(2);
    }
    for f in &files {
        let data = std::fs::read(f).unwrap_or_else(|e| panic!("{f}: {e}"));
        splatmark_fuzz::run(&target, &data);
    }
    println!("{target}: {} inputs, no finding", files.len());
}
