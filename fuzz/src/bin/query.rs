fn main() {
    afl::fuzz!(|data: &[u8]| {
        splatmark_fuzz::run("query", data);
    });
}
