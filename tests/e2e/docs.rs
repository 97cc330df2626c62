//! The documentation kept true by running it: every shell command in README.md's `sh` code
//! blocks runs, in order, in one scratch folder, as a user would type it (with a small capture
//! in place of the big one), and exits as documented (0, or the `exit N` its comment names); and
//! every option that a `--help` lists is described in the README or under `docs/`.

use std::path::{Path, PathBuf};
use std::process::Command;

use multiscopic_tests::{binary, run, shared_data, temp_dir, workspace_root};

/// One command of a README code block.
#[derive(Debug)]
struct DocCommand {
    /// 1-based line of the README where the command starts.
    line: usize,
    words: Vec<String>,
    /// The exit code the README documents for it.
    exit_code: i32,
}

/// Splits a shell line into words: blanks separate, single and double quotes group.
fn shell_words(text: &str) -> Vec<String> {
    let mut words = Vec::new();
    let mut word = String::new();
    let mut in_word = false;
    let mut quote: Option<char> = None;
    for c in text.chars() {
        match quote {
            Some(q) if c == q => quote = None,
            Some(_) => word.push(c),
            None if c == '\'' || c == '"' => {
                quote = Some(c);
                in_word = true;
            }
            None if c.is_whitespace() => {
                if in_word {
                    words.push(std::mem::take(&mut word));
                    in_word = false;
                }
            }
            None => {
                word.push(c);
                in_word = true;
            }
        }
    }
    assert!(quote.is_none(), "unclosed quote in README command: {text}");
    if in_word {
        words.push(word);
    }
    words
}

/// The commands of every ```` ```sh ```` block: comment lines dropped, `\` continuations joined,
/// a trailing `# … exit N …` comment read as the documented exit code.
fn readme_commands(readme: &str) -> Vec<DocCommand> {
    let mut commands = Vec::new();
    let mut in_sh = false;
    let mut pending: Option<(usize, String)> = None;
    for (index, raw) in readme.lines().enumerate() {
        let trimmed = raw.trim();
        if trimmed.starts_with("```") {
            in_sh = trimmed == "```sh";
            continue;
        }
        if !in_sh || trimmed.is_empty() || trimmed.starts_with('#') {
            continue;
        }
        let (code, comment) = match raw.find(" #") {
            Some(at) => (&raw[..at], &raw[at + 2..]),
            None => (raw, ""),
        };
        let (start, mut text) = pending.take().unwrap_or((index + 1, String::new()));
        let code = code.trim_end();
        if let Some(head) = code.strip_suffix('\\') {
            text.push_str(head);
            text.push(' ');
            pending = Some((start, text));
            continue;
        }
        text.push_str(code);
        let exit_code = comment
            .split("exit ")
            .nth(1)
            .and_then(|rest| rest.chars().next())
            .and_then(|c| c.to_digit(10))
            .map_or(0, |d| d as i32);
        commands.push(DocCommand {
            line: start,
            words: shell_words(&text),
            exit_code,
        });
    }
    assert!(pending.is_none(), "README ends inside a continued command");
    commands
}

/// A capture small enough for the test: the simulated resolution replaced, one sample per pixel.
fn small_capture(args: &mut Vec<String>, program: &str) {
    let records = program == "record" && args.first().map(String::as_str) != Some("import");
    let demo = program == "replay" && args.first().map(String::as_str) == Some("demo");
    if !(records || demo) {
        return;
    }
    match args.iter().position(|a| a == "--resolution") {
        Some(at) if at + 1 < args.len() => args[at + 1] = "160x96".into(),
        _ => args.extend(["--resolution".into(), "160x96".into()]),
    }
    if records && !args.iter().any(|a| a == "--samples-per-pixel") {
        args.extend(["--samples-per-pixel".into(), "1".into()]);
    }
}

/// `../shared/...` as the README writes it (from the checkout) made absolute for the scratch folder.
fn shared_path(arg: &str) -> String {
    match arg.strip_prefix("../shared/data/") {
        Some(rest) => {
            let path = shared_data().join(rest);
            assert!(
                path.exists(),
                "the README's command needs {} (the evaluation data beside the checkout, ../shared/data): missing",
                path.display()
            );
            path.to_string_lossy().into_owned()
        }
        None => arg.to_string(),
    }
}

#[test]
fn every_readme_command_runs_and_exits_as_documented() {
    let readme = std::fs::read_to_string(workspace_root().join("README.md")).unwrap_or_else(|e| panic!("{e}"));
    let commands = readme_commands(&readme);
    assert!(
        commands.len() >= 10,
        "only {} commands found in the README's sh blocks",
        commands.len()
    );
    let dir = temp_dir();
    let bin_dir = binary("replay").parent().map(Path::to_path_buf).unwrap_or_default();
    // The binaries first on PATH and no viewer: `--rerun spawn` must say so and exit 3.
    let path = format!("{}:/usr/bin:/bin", bin_dir.display());
    let mut ran = 0;
    for command in &commands {
        let words = &command.words;
        let (program, mut args): (&str, Vec<String>) = match words.first().map(String::as_str) {
            Some("cargo") => {
                // `cargo run --release -p NAME -- ARGS` runs the binary NAME.
                let name = words.iter().position(|w| w == "-p").and_then(|at| words.get(at + 1));
                let rest = words
                    .iter()
                    .position(|w| w == "--")
                    .map_or(&words[..0], |at| &words[at + 1..]);
                match name.map(String::as_str) {
                    Some(name @ ("record" | "replay")) => (name, rest.to_vec()),
                    other => panic!("README line {}: cargo command for {other:?}", command.line),
                }
            }
            Some(name @ ("record" | "replay")) => (name, words[1..].to_vec()),
            Some("scripts/test.sh") => {
                println!(
                    "README line {}: scripts/test.sh is the command running this test: not run again",
                    command.line
                );
                continue;
            }
            Some("ros2") => {
                // `ros2 bag record -s mcap -o NAME TOPICS` runs on the robot; here `rosbags` writes
                // a bag of that shape (the camera streaming through the moves, TF, joints) from a
                // dev scene, and the README's topics must be the ones it holds.
                let name = words
                    .iter()
                    .position(|w| w == "-o")
                    .and_then(|at| words.get(at + 1))
                    .unwrap_or_else(|| panic!("README line {}: `ros2 bag record` without -o", command.line));
                let bag = dir.path().join(name);
                let output = run(Command::new(multiscopic_tests::python_with_mcap())
                    .arg(workspace_root().join("tests/python/write_ros2_capture.py"))
                    .arg(multiscopic_tests::middlebury_dev("Aloe"))
                    .arg(&bag)
                    .args(["--views", "view1@0,view0@-1,view2@1"]));
                multiscopic_tests::assert_success(&output, "write_ros2_capture.py");
                let written = std::fs::read_to_string(bag.join("metadata.yaml")).unwrap_or_else(|e| panic!("{e}"));
                for topic in words.iter().filter(|w| w.starts_with('/')) {
                    assert!(
                        written.contains(&format!("name: {topic}\n")),
                        "README line {}: the bag of the test has no {topic}",
                        command.line
                    );
                }
                ran += 1;
                continue;
            }
            Some("rerun") => {
                // Opens a window: the test checks that the files it opens exist.
                for file in words[1..].iter().filter(|w| !w.starts_with('-')) {
                    assert!(
                        dir.path().join(file).exists(),
                        "README line {}: `rerun` opens {file}, which the commands before it did not write",
                        command.line
                    );
                }
                println!(
                    "README line {}: `rerun` opens a window: only its files checked",
                    command.line
                );
                continue;
            }
            other => panic!(
                "README line {}: unknown program {other:?}: teach this test to run it",
                command.line
            ),
        };
        small_capture(&mut args, program);
        let args: Vec<String> = args.iter().map(|a| shared_path(a)).collect();
        let output = run(Command::new(bin_dir.join(program))
            .args(&args)
            .current_dir(dir.path())
            .env("PATH", &path));
        assert_eq!(
            output.status.code(),
            Some(command.exit_code),
            "README line {}: `{program} {}` exited {:?}, documented {}\nstderr:\n{}",
            command.line,
            args.join(" "),
            output.status.code(),
            command.exit_code,
            String::from_utf8_lossy(&output.stderr)
        );
        ran += 1;
    }
    assert!(ran >= 10, "only {ran} README commands ran");
}

/// The options a `--help` lists (`--name` at the start of an option line).
fn help_options(program: &str, args: &[&str]) -> Vec<String> {
    let output = run(Command::new(binary(program)).args(args).arg("--help"));
    assert!(output.status.success(), "{program} {args:?} --help failed");
    let text = String::from_utf8_lossy(&output.stdout).into_owned();
    let mut options = Vec::new();
    for line in text.lines() {
        let line = line.trim_start();
        if !line.starts_with('-') {
            continue;
        }
        if let Some(long) = line
            .split([' ', ',', '=', '<'])
            .find(|w| w.starts_with("--") && w.len() > 2)
        {
            options.push(long.to_string());
        }
    }
    options
}

/// Subcommands a `--help` lists under "Commands:".
fn help_subcommands(program: &str) -> Vec<String> {
    let output = run(Command::new(binary(program)).arg("--help"));
    let text = String::from_utf8_lossy(&output.stdout).into_owned();
    text.lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| l.starts_with("  "))
        .filter_map(|l| l.split_whitespace().next().map(str::to_string))
        .filter(|name| name != "help")
        .collect()
}

fn documentation() -> String {
    let root = workspace_root();
    let mut files: Vec<PathBuf> = vec![root.join("README.md"), root.join("fuse/weights/README.md")];
    let docs = std::fs::read_dir(root.join("docs")).unwrap_or_else(|e| panic!("docs/: {e}"));
    files.extend(
        docs.filter_map(Result::ok)
            .map(|e| e.path())
            .filter(|p| p.extension().is_some_and(|x| x == "md")),
    );
    files
        .iter()
        .map(|f| std::fs::read_to_string(f).unwrap_or_else(|e| panic!("{}: {e}", f.display())))
        .collect::<Vec<_>>()
        .join("\n")
}

/// Whether `text` names `option` as a whole word (`--out` is not found in `--out-mcap`).
fn mentions(text: &str, option: &str) -> bool {
    text.match_indices(option).any(|(at, _)| {
        let next = text[at + option.len()..].chars().next();
        !next.is_some_and(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
    })
}

#[test]
fn every_option_of_every_help_is_documented() {
    let docs = documentation();
    let mut checked = 0;
    let mut missing = Vec::new();
    for program in ["record", "replay"] {
        let mut invocations: Vec<Vec<String>> = vec![vec![]];
        invocations.extend(help_subcommands(program).into_iter().map(|s| vec![s]));
        assert!(invocations.len() >= 2, "{program} --help lists no subcommands");
        for args in invocations {
            let args: Vec<&str> = args.iter().map(String::as_str).collect();
            for option in help_options(program, &args) {
                if option == "--help" || option == "--version" {
                    continue;
                }
                checked += 1;
                if !mentions(&docs, &option) {
                    missing.push(format!("{program} {} {option}", args.join(" ")));
                }
            }
        }
    }
    assert!(checked >= 40, "only {checked} options found in the --help texts");
    assert!(
        missing.is_empty(),
        "options in --help described nowhere in README.md or docs/: {missing:#?}"
    );
}

#[test]
fn the_readme_parser_reads_continuations_quotes_and_exit_codes() {
    let text = "x\n```sh\n# a comment\nreplay a.mcap --config '{\"a\": 1}'   # exit 3 when so\nrecord \\\n  -o b.mcap\n```\n```text\nnot run\n```\n";
    let commands = readme_commands(text);
    assert_eq!(commands.len(), 2);
    assert_eq!(commands[0].words, ["replay", "a.mcap", "--config", "{\"a\": 1}"]);
    assert_eq!(commands[0].exit_code, 3);
    assert_eq!(commands[0].line, 4);
    assert_eq!(commands[1].words, ["record", "-o", "b.mcap"]);
    assert_eq!(commands[1].exit_code, 0);
}
