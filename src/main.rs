fn main() -> std::process::ExitCode {
    splatmark::alloc::tune();
    splatmark::cli::main()
}
