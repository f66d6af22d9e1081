//! `nak serve` as a child process on an ephemeral loopback port, its JSON log collected as it runs.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::mpsc;
use std::time::Duration;

pub struct ServeProcess {
    child: Child,
    pub address: String,
    lines: mpsc::Receiver<String>,
    log: Vec<String>,
}

/// The `nak` binary, with a plain (uncoloured, backtrace-free) error output.
pub fn nak() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_nak"));
    c.env("RUST_BACKTRACE", "0").env("NO_COLOR", "1");
    c
}

impl ServeProcess {
    /// Runs `command` (a `nak serve` or a wrapper that ends by executing one) with `--listen
    /// 127.0.0.1:0 --log-format json` appended, and waits until it listens.
    pub fn start(command: Command) -> Self {
        Self::start_on(command, "127.0.0.1:0")
    }

    /// As [`Self::start`], listening on `address`.
    pub fn start_on(mut command: Command, address: &str) -> Self {
        let mut child = command
            .args(["--listen", address, "--log-format", "json"])
            .stderr(Stdio::piped())
            .spawn()
            .expect("start nak serve");
        let stderr = child.stderr.take().expect("stderr is piped");
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let mut server = Self {
            child,
            address: String::new(),
            lines,
            log: Vec::new(),
        };
        server.address = server
            .wait_for(Duration::from_secs(120), |record| {
                record["fields"]["message"] == "listening"
            })
            .and_then(|record| record["fields"]["address"].as_str().map(str::to_owned))
            .unwrap_or_else(|| panic!("nak serve did not start listening; its log: {:#?}", server.log));
        server
    }

    /// The first log record (read until `timeout`) that `matches`; every line read is kept in the log.
    pub fn wait_for(
        &mut self,
        timeout: Duration,
        matches: impl Fn(&serde_json::Value) -> bool,
    ) -> Option<serde_json::Value> {
        let deadline = std::time::Instant::now() + timeout;
        while let Ok(line) = self
            .lines
            .recv_timeout(deadline.saturating_duration_since(std::time::Instant::now()))
        {
            self.log.push(line.clone());
            if let Ok(record) = serde_json::from_str::<serde_json::Value>(&line)
                && matches(&record)
            {
                return Some(record);
            }
        }
        None
    }

    /// Every log line read so far.
    pub fn log(&self) -> &[String] {
        &self.log
    }

    /// Sends SIGTERM and waits for the exit; returns it with the whole log.
    pub fn stop(mut self) -> (ExitStatus, Vec<String>) {
        let killed = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status()
            .expect("kill");
        assert!(killed.success());
        let exit = self.child.wait().expect("wait for nak serve");
        self.log.extend(self.lines.iter());
        (exit, std::mem::take(&mut self.log))
    }
}

impl Drop for ServeProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
