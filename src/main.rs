fn main() -> std::process::ExitCode {
    splatmark::cli::main()
}
