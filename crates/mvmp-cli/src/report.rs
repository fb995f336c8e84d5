//! How an error reads on the command line.

/// `err` and its causes on one line, each cause once: library errors often spell out their cause
/// already, and anyhow's `{:#}` would repeat it.
pub fn message(err: &anyhow::Error) -> String {
    let mut msg = err.to_string();
    for cause in err.chain().skip(1) {
        let c = cause.to_string();
        if !msg.contains(&c) {
            msg = format!("{msg}: {c}");
        }
    }
    msg
}

#[cfg(test)]
mod tests {
    use super::message;

    #[test]
    fn a_cause_the_message_spells_out_is_said_once() {
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "no such file");
        let err = anyhow::Error::new(io).context("f.npz: no such file");
        assert_eq!(message(&err), "f.npz: no such file");
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "no such file");
        let err = anyhow::Error::new(io).context("reading f.npz");
        assert_eq!(message(&err), "reading f.npz: no such file");
    }
}
