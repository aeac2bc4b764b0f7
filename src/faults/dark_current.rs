//! `dark_current` (not yet implemented).
