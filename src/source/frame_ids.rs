//! Numbering a camera's frames from its own frame counter (GenICam block / frame id): frames
//! the camera or the transport lost show as gaps, and a counter that wraps or is reset does
//! not turn into billions of "lost" frames.
//!
//! GigE Vision 1.x block ids are 16-bit and wrap from 65535 to 1 (0 is reserved); GigE Vision
//! 2 and USB3 Vision ids are 64-bit; a camera restarted by its own watchdog starts again at 0
//! or 1; an incomplete buffer may carry an id of 0. Steps of 1..=`max_gap + 1` are the normal
//! case (`step - 1` frames lost); anything else is a jump: numbering continues, and the frames
//! lost in the jump, if any, cannot be counted.

/// Where one frame id lands in the stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Placement {
    /// The frame's stream sequence number, after `skipped` frames the camera did not deliver
    /// (their ids are the `skipped` ids before this one).
    Next { seq: u64, skipped: u64 },
    /// The counter went back, or forward by more than the largest gap: it wrapped or was
    /// reset. The frame gets the next sequence number.
    Jump { seq: u64, from: u64, to: u64 },
}

/// Stream sequence numbers from camera frame ids.
#[derive(Debug, Clone)]
pub struct FrameIds {
    last_id: Option<u64>,
    next_seq: u64,
    max_gap: u64,
}

impl FrameIds {
    /// `max_gap`: the largest run of lost frames read as a gap rather than a counter jump.
    pub fn new(max_gap: u64) -> FrameIds {
        FrameIds { last_id: None, next_seq: 0, max_gap }
    }

    /// Frames lost before `id` if it continues the sequence (`Some(0)` = the next frame),
    /// `None` if it does not (a jump, a repeat, or the first frame).
    pub fn step(&self, id: u64) -> Option<u64> {
        let last = self.last_id?;
        let step = if last <= 0xFFFF && id < last && last + self.max_gap >= 0xFFFF && id <= self.max_gap + 1 {
            // A 16-bit GigE Vision 1.x block id wrapping from 65535 to 1 (0 is skipped).
            (0xFFFF - last) + id
        } else {
            id.wrapping_sub(last)
        };
        (1..=self.max_gap + 1).contains(&step).then(|| step - 1)
    }

    /// Number the frame with camera id `id`.
    pub fn place(&mut self, id: u64) -> Placement {
        let placement = match (self.last_id, self.step(id)) {
            (None, _) => Placement::Next { seq: 0, skipped: 0 },
            (Some(_), Some(skipped)) => Placement::Next { seq: self.next_seq + skipped, skipped },
            (Some(from), None) => Placement::Jump { seq: self.next_seq, from, to: id },
        };
        let seq = match placement {
            Placement::Next { seq, .. } | Placement::Jump { seq, .. } => seq,
        };
        self.next_seq = seq + 1;
        self.last_id = Some(id);
        placement
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn contiguous_ids_number_from_zero_whatever_the_first_id() {
        let mut ids = FrameIds::new(64);
        for (k, id) in (500..510).enumerate() {
            assert_eq!(ids.place(id), Placement::Next { seq: k as u64, skipped: 0 });
        }
    }

    #[test]
    fn a_gap_counts_the_lost_frames() {
        let mut ids = FrameIds::new(64);
        ids.place(7);
        ids.place(8);
        assert_eq!(ids.place(12), Placement::Next { seq: 5, skipped: 3 });
        assert_eq!(ids.place(13), Placement::Next { seq: 6, skipped: 0 });
    }

    #[test]
    fn a_16_bit_block_id_wraps_from_65535_to_1() {
        let mut ids = FrameIds::new(64);
        ids.place(65534);
        ids.place(65535);
        assert_eq!(ids.place(1), Placement::Next { seq: 2, skipped: 0 });
        assert_eq!(ids.place(3), Placement::Next { seq: 4, skipped: 1 });
    }

    #[test]
    fn a_reset_or_a_zero_id_is_a_jump_not_billions_of_lost_frames() {
        let mut ids = FrameIds::new(64);
        for id in 1000..1135 {
            ids.place(id);
        }
        // An incomplete buffer with id 0, then the camera goes on: two jumps, no gaps.
        assert_eq!(ids.place(0), Placement::Jump { seq: 135, from: 1134, to: 0 });
        assert_eq!(ids.place(1136), Placement::Jump { seq: 136, from: 0, to: 1136 });
        assert_eq!(ids.place(1137), Placement::Next { seq: 137, skipped: 0 });
        // Far ahead (more than the largest gap) and a repeat are jumps too.
        assert_eq!(ids.place(1137 + 66), Placement::Jump { seq: 138, from: 1137, to: 1203 });
        assert_eq!(ids.place(1203), Placement::Jump { seq: 139, from: 1203, to: 1203 });
        assert_eq!(ids.step(1204), Some(0));
        assert_eq!(ids.step(u64::MAX), None);
    }
}
