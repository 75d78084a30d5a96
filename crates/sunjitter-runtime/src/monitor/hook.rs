//! The alert command: run for every alert event with the alert JSON on stdin, one at a time on
//! its own thread, killed after a time limit. The writer thread only queues (never waits);
//! failures come back as one-line reasons for `/log`.
//!
//! The command runs in a process group of its own, and a command over its time limit is killed
//! with its whole group: a shell script's children go with it instead of living on.

use std::io::Write;
use std::os::unix::process::CommandExt;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{channel, sync_channel, Receiver, Sender, SyncSender, TrySendError};
use std::time::{Duration, Instant};

/// Alerts queued for the command at most; more are reported as failures, not run.
const QUEUE: usize = 64;

/// The writer thread's end.
pub struct Hook {
    tx: SyncSender<String>,
    failures_tx: Sender<String>,
    failures: Receiver<String>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Hook {
    /// Start the hook thread for `command` (program and arguments).
    pub fn start(command: Vec<String>, timeout: Duration) -> std::io::Result<Hook> {
        let (tx, rx) = sync_channel::<String>(QUEUE);
        let (failures_tx, failures) = channel();
        let report = failures_tx.clone();
        let thread = std::thread::Builder::new()
            .name("sunjitter-alert-command".into())
            .spawn(move || {
                while let Ok(json) = rx.recv() {
                    if let Err(reason) = run_command(&command, &json, timeout) {
                        tracing::error!("alert command: {reason}");
                        let _ = report.send(reason);
                    }
                }
            })?;
        Ok(Hook {
            tx,
            failures_tx,
            failures,
            thread: Some(thread),
        })
    }

    /// Queue one alert; never waits.
    pub fn offer(&self, json: String) {
        if let Err(e) = self.tx.try_send(json) {
            let reason = match e {
                TrySendError::Full(_) => "queue full: alert not passed to the command",
                TrySendError::Disconnected(_) => "command thread gone: alert not passed on",
            };
            tracing::error!("alert command: {reason}");
            let _ = self.failures_tx.send(reason.to_string());
        }
    }

    /// Failures reported since the last call.
    pub fn failures(&self) -> Vec<String> {
        self.failures.try_iter().collect()
    }

    /// Let the queued alerts run (each within its time limit), then stop. Returns the
    /// failures not yet collected.
    pub fn finish(mut self) -> Vec<String> {
        let (dead_tx, _) = sync_channel(1);
        drop(std::mem::replace(&mut self.tx, dead_tx));
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        self.failures()
    }
}

/// Run `command` with `input` on stdin; Err is a one-line reason.
pub fn run_command(command: &[String], input: &str, timeout: Duration) -> Result<(), String> {
    let (program, args) = command
        .split_first()
        .ok_or_else(|| "no command configured".to_string())?;
    let mut child = Command::new(program)
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .process_group(0)
        .spawn()
        .map_err(|e| format!("cannot run {program}: {e}"))?;
    if let Some(mut stdin) = child.stdin.take() {
        // A command that does not read its input is not a failure.
        match stdin.write_all(input.as_bytes()) {
            Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => {
                kill(&mut child);
                return Err(format!("{program}: cannot write the alert: {e}"));
            }
            _ => {}
        }
    }
    let deadline = Instant::now() + timeout;
    loop {
        match child.try_wait() {
            Ok(Some(status)) if status.success() => return Ok(()),
            Ok(Some(status)) => return Err(format!("{program} failed: {status}")),
            Ok(None) if Instant::now() >= deadline => {
                kill(&mut child);
                return Err(format!(
                    "{program} killed after the {} s time limit",
                    timeout.as_secs_f64()
                ));
            }
            // A child has no blocking wait with a deadline in std: poll it.
            Ok(None) => std::thread::sleep(Duration::from_millis(10)),
            Err(e) => return Err(format!("{program}: {e}")),
        }
    }
}

/// Kill the command and everything it started (its process group, whose id is its pid).
fn kill(child: &mut Child) {
    match libc::pid_t::try_from(child.id()) {
        // SAFETY: kill(2) has no memory-safety preconditions. The group cannot have been
        // reused yet: its leader is our child, not reaped until the wait below.
        Ok(pgid) if pgid > 1 => unsafe {
            libc::kill(-pgid, libc::SIGKILL);
        },
        _ => {
            let _ = child.kill();
        }
    }
    let _ = child.wait();
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sh(script: &str) -> Vec<String> {
        vec!["sh".into(), "-c".into(), script.into()]
    }

    #[test]
    fn the_command_gets_the_alert_on_stdin() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("got.json");
        let cmd = sh(&format!("cat > '{}'", out.display()));
        run_command(&cmd, "{\"kind\":\"jump_px\"}\n", Duration::from_secs(10)).unwrap();
        assert_eq!(
            std::fs::read_to_string(&out).unwrap(),
            "{\"kind\":\"jump_px\"}\n"
        );
    }

    #[test]
    fn failures_and_overruns_are_reported_in_one_line() {
        let e = run_command(&sh("exit 3"), "{}", Duration::from_secs(10)).unwrap_err();
        assert!(e.contains("exit status: 3"), "{e}");
        let e = run_command(&sh("sleep 30"), "{}", Duration::from_millis(100)).unwrap_err();
        assert!(e.contains("killed after"), "{e}");
        let e = run_command(
            &["/nonexistent/alert-command".into()],
            "{}",
            Duration::from_secs(1),
        )
        .unwrap_err();
        assert!(e.contains("cannot run"), "{e}");
    }

    #[test]
    fn queued_alerts_run_in_order_and_failures_come_back() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("all.jsonl");
        let hook = Hook::start(
            sh(&format!(
                "read line; echo \"$line\" >> '{}'; [ \"$line\" != bad ]",
                out.display()
            )),
            Duration::from_secs(10),
        )
        .unwrap();
        for line in ["one", "bad", "two"] {
            hook.offer(format!("{line}\n"));
        }
        let failures = hook.finish();
        assert_eq!(std::fs::read_to_string(&out).unwrap(), "one\nbad\ntwo\n");
        assert_eq!(failures.len(), 1, "{failures:?}");
        assert!(failures[0].contains("exit status: 1"), "{failures:?}");
    }
}
