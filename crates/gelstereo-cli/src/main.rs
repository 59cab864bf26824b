//! `gelstereo`: the command-line tool. Thin: argument parsing, progress and error context; the work is
//! done by the library crates.

fn main() {}
