//! RabbitMQ's duration strings (`x-max-age`, the `max-age` policy key):
//! digits then one unit, read the way RabbitMQ 3.10 reads them. Used by
//! streams' arguments and by policies.

/// Why a duration string is not one.
pub enum DurationError {
    /// No digits first: RabbitMQ 3.10 fails inside its parser (541).
    NoNumber,
    /// Zero, or a unit it does not know (406).
    Invalid,
}

/// RabbitMQ's duration (`check_max_age`): digits then one of `Y M D h m s`
/// (a year is 365 days, a month 30), in milliseconds; zero is refused.
pub fn duration_ms(text: &[u8]) -> Result<u64, DurationError> {
    let digits = text.iter().take_while(|b| b.is_ascii_digit()).count();
    if digits == 0 {
        return Err(DurationError::NoNumber);
    }
    let value: u64 = std::str::from_utf8(&text[..digits])
        .ok()
        .and_then(|d| d.parse().ok())
        .ok_or(DurationError::Invalid)?;
    let unit_s: u64 = match &text[digits..] {
        b"Y" => 365 * 86_400,
        b"M" => 30 * 86_400,
        b"D" => 86_400,
        b"h" => 3_600,
        b"m" => 60,
        b"s" => 1,
        _ => return Err(DurationError::Invalid),
    };
    if value == 0 {
        return Err(DurationError::Invalid);
    }
    Ok(value.saturating_mul(unit_s).saturating_mul(1000))
}

/// A `max-age` duration (`x-max-age`, the `max-age` policy key) in
/// milliseconds, `None` if it is not one.
pub fn max_age_ms(text: &[u8]) -> Option<u64> {
    duration_ms(text).ok()
}
