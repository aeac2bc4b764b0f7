//! Campaign timelines frame by frame: the [`CampaignController`] driving a real chain, with
//! triggers injected as a recorded trigger log (the replay input). Checks which frames have
//! which effect state, the ramp values, the seeded random events, the log events, and that
//! validation names the line and the field of every problem. Every example campaign in
//! `hil/campaigns/` must validate.

use faultcam::FaultConfig;
use faultcam::control::Controller;
use faultcam::faults::chain::Chain;
use faultcam::schedule::{Campaign, CampaignController};
use faultcam::trigger::TriggerReplay;
use serde_json::Value;

/// State of one chain entry (by config index) on one frame.
#[derive(Debug, Clone, PartialEq)]
struct EntryState {
    enabled: bool,
    params: Vec<(&'static str, f64)>,
}

struct Run {
    /// Per frame, per config index.
    states: Vec<Vec<EntryState>>,
    events: Vec<Value>,
}

impl Run {
    fn enabled(&self, index: usize) -> Vec<u64> {
        (0..self.states.len() as u64).filter(|&s| self.states[s as usize][index].enabled).collect()
    }
    fn param(&self, seq: usize, index: usize, name: &str) -> f64 {
        self.states[seq][index].params.iter().find(|(n, _)| *n == name).unwrap().1
    }
    fn events_of(&self, kind: &str) -> Vec<&Value> {
        self.events.iter().filter(|e| e["event"] == kind).collect()
    }
}

fn parse(text: &str) -> (FaultConfig, Campaign) {
    let cfg = FaultConfig::parse(text, "c.toml").unwrap();
    let c = Campaign::from_config(&cfg).unwrap_or_else(|e| panic!("{e}"));
    (cfg, c)
}

/// Drive `frames` frames at `fps` (stream time `seq / fps`), with trigger commands
/// `(frame, command)` applied at those frames.
fn drive(text: &str, frames: u64, fps: f64, triggers: &[(u64, &str)]) -> Run {
    let (cfg, campaign) = parse(text);
    let mut chain = Chain::from_config(&cfg).unwrap();
    let input = if triggers.is_empty() {
        None
    } else {
        let log: String = triggers
            .iter()
            .enumerate()
            .map(|(i, (f, c))| {
                format!(
                    "{}\n",
                    serde_json::json!({"record": "event", "event": "trigger", "seq": f, "cmd_seq": i, "command": c})
                )
            })
            .collect();
        let r = TriggerReplay::from_text(&log, "triggers.jsonl", campaign.catalog()).unwrap_or_else(|e| panic!("{e}"));
        Some(Box::new(r) as Box<dyn faultcam::trigger::TriggerInput>)
    };
    let mut ctl = CampaignController::new(campaign, input);
    let mut events = Vec::new();
    let mut states = Vec::new();
    for seq in 0..frames {
        let t_ns = (seq as f64 * 1e9 / fps).round() as u64;
        ctl.before_frame(seq, t_ns, &mut chain, &mut events).unwrap();
        let mut st: Vec<(usize, EntryState)> = chain
            .entries()
            .iter()
            .map(|e| {
                (
                    e.index,
                    EntryState { enabled: e.enabled, params: e.params.iter().map(|(s, v)| (s.name, v)).collect() },
                )
            })
            .collect();
        st.sort_by_key(|(i, _)| *i);
        states.push(st.into_iter().map(|(_, s)| s).collect());
    }
    ctl.finish(&mut events);
    Run { states, events }
}

#[test]
fn frame_events_with_duration_and_repeats() {
    let run = drive(
        "[[effects]]\nname = \"gain_offset\"\n\
         [[events]]\nname = \"dim\"\neffect = \"gain_offset\"\nat_frame = 3\nduration_frames = 2\nrepeat = 3\nperiod_frames = 5\n\
         [events.params]\ngain = 0.5\n",
        20,
        30.0,
        &[],
    );
    // Event-only effects start disabled and run only while an occurrence is active.
    assert_eq!(run.enabled(0), vec![3, 4, 8, 9, 13, 14]);
    assert_eq!(run.param(3, 0, "gain"), 0.5);
    assert_eq!(run.param(5, 0, "gain"), 1.0, "back to the baseline after the event");
    let starts: Vec<u64> = run.events_of("event_start").iter().map(|e| e["seq"].as_u64().unwrap()).collect();
    let stops: Vec<u64> = run.events_of("event_stop").iter().map(|e| e["seq"].as_u64().unwrap()).collect();
    assert_eq!(starts, vec![3, 8, 13]);
    assert_eq!(stops, vec![5, 10, 15]);
    assert!(run.events_of("event_stop").iter().all(|e| e["reason"] == "duration" && e["frames"] == 2));
    assert_eq!(run.events_of("event_start")[2]["occurrence"], 2);
}

#[test]
fn time_events_follow_stream_time() {
    // 10 fps: t = seq/10 s; the event covers t in [0.5, 0.8) → frames 5, 6, 7; repeats every 1 s.
    let run = drive(
        "[[effects]]\nname = \"gaussian_noise\"\n\
         [[events]]\nname = \"noisy\"\neffect = \"gaussian_noise\"\nat_s = 0.5\nduration_s = 0.3\nrepeat = \"forever\"\nperiod_s = 1.0\n\
         [events.params]\nsigma_dn = 7.0\n",
        30,
        10.0,
        &[],
    );
    assert_eq!(run.enabled(0), vec![5, 6, 7, 15, 16, 17, 25, 26, 27]);
    assert_eq!(run.param(6, 0, "sigma_dn"), 7.0);
    // The end of the stream closes the last occurrence... none is open at frame 29.
    assert!(run.events_of("event_stop").iter().all(|e| e["reason"] == "duration"));
}

#[test]
fn ramps_linear_keyframes_and_steps() {
    let run = drive(
        "[[effects]]\nname = \"defocus\"\n\
         [[effects]]\nname = \"gain_offset\"\nenabled = true\n\
         [[events]]\nname = \"blur\"\neffect = \"defocus\"\nat_frame = 2\nduration_frames = 4\n\
         [events.params]\nsigma_px = { linear = [0.0, 4.0] }\n\
         [[events]]\nname = \"pulse\"\neffect = \"gain_offset\"\nat_s = 1.0\nduration_s = 1.0\n\
         [events.params]\ngain = { keyframes = [[0.0, 1.0], [0.5, 3.0], [1.0, 1.0]] }\n\
         offset_dn = { steps = [[0.0, 10], [0.5, -10]] }\n",
        24,
        10.0,
        &[],
    );
    // Linear over the duration (frames): u/D with u = 0..3, D = 4.
    let sig: Vec<f64> = (2..6).map(|s| run.param(s, 0, "sigma_px")).collect();
    assert_eq!(sig, vec![0.0, 1.0, 2.0, 3.0]);
    assert_eq!(run.enabled(0), vec![2, 3, 4, 5]);
    // Keyframes in seconds from t = 1.0 s (frame 10): 1 → 3 at 0.5 s → 1 at 1.0 s.
    let gains: Vec<f64> = (10..20).map(|s| run.param(s, 1, "gain")).collect();
    for (k, g) in gains.iter().enumerate() {
        let u = k as f64 / 10.0;
        let want = if u <= 0.5 { 1.0 + 4.0 * u } else { 3.0 - 4.0 * (u - 0.5) };
        assert!((g - want).abs() < 1e-9, "frame {}: gain {g}, want {want}", 10 + k);
    }
    let offs: Vec<f64> = (9..21).map(|s| run.param(s, 1, "offset_dn")).collect();
    assert_eq!(offs, vec![0.0, 10.0, 10.0, 10.0, 10.0, 10.0, -10.0, -10.0, -10.0, -10.0, -10.0, 0.0]);
    // The explicitly enabled effect stays on; only its parameters follow the event.
    assert_eq!(run.enabled(1).len(), 24);
    // Every change is logged as an effect_state event with the frame seq.
    let changes = run.events_of("effect_state");
    assert!(changes.iter().any(|e| e["seq"] == 3 && e["effect"] == "defocus" && e["params"]["sigma_px"] == 1.0));
}

#[test]
fn random_events_are_seeded_and_follow_their_rate() {
    let text = |seed: u64, start: &str| {
        format!(
            "seed = {seed}\n[[effects]]\nname = \"cosmic_rays\"\n\
             [[events]]\nname = \"storm\"\neffect = \"cosmic_rays\"\n{start}\nduration_frames = 1\n\
             [events.params]\nrate = 1e-4\n"
        )
    };
    let n = 2000u64;
    let a = drive(&text(1, "p_per_frame = 0.2"), n, 100.0, &[]);
    let b = drive(&text(1, "p_per_frame = 0.2"), n, 100.0, &[]);
    let c = drive(&text(2, "p_per_frame = 0.2"), n, 100.0, &[]);
    assert_eq!(a.enabled(0), b.enabled(0), "same seed, same frames");
    assert_ne!(a.enabled(0), c.enabled(0), "the seed matters");
    // Each frame fires with p = 0.2 unless the previous frame's one-frame event is still on:
    // expected fraction p (an active event ends before the next frame draws). Binomial sd ≈ 18.
    let k = a.enabled(0).len() as f64;
    assert!((k - 0.2 * n as f64).abs() < 5.0 * 17.9, "{k} of {n}");
    // rate_hz = 5 at 100 fps: per frame 1 - exp(-0.05) ≈ 0.0488; 20 s → ≈ 97.5 (sd ≈ 9.6).
    let r = drive(&text(3, "rate_hz = 5.0"), n, 100.0, &[]);
    let k = r.enabled(0).len() as f64;
    let p = 1.0 - (-0.05f64).exp();
    assert!((k - p * n as f64).abs() < 5.0 * (n as f64 * p * (1.0 - p)).sqrt(), "{k}");
    assert!(r.events_of("event_start").iter().all(|e| e["cause"] == "random"));
    // A window confines the draws.
    let w = drive(&text(4, "p_per_frame = 0.5\nwindow_frames = [100, 200]"), 400, 100.0, &[]);
    assert!(w.enabled(0).iter().all(|s| (100..201).contains(s)), "{:?}", w.enabled(0));
    assert!(!w.enabled(0).is_empty());
}

#[test]
fn triggered_blooming_for_two_seconds_and_commands() {
    let text = "[[effects]]\nname = \"blooming\"\n\
                [[effects]]\nname = \"gain_offset\"\nenabled = true\n\
                [[events]]\nname = \"glint\"\neffect = \"blooming\"\ntrigger = \"flash\"\nduration_s = 2.0\n\
                [events.params]\nspread_px = 4.0\n";
    // 10 fps: START at frame 7 (t = 0.7 s) → active while t < 2.7 s, i.e. frames 7..=26.
    let run = drive(text, 40, 10.0, &[(7, "START flash"), (30, "SET gain_offset#1.gain 2"), (33, "MARK done")]);
    assert_eq!(run.enabled(0), (7..27).collect::<Vec<u64>>());
    assert_eq!(run.param(8, 0, "spread_px"), 4.0);
    let start = run.events_of("event_start");
    assert_eq!((start[0]["seq"].as_u64(), start[0]["cause"].as_str()), (Some(7), Some("trigger")));
    let stop = run.events_of("event_stop");
    assert_eq!((stop[0]["seq"].as_u64(), stop[0]["reason"].as_str()), (Some(27), Some("duration")));
    // SET changes the baseline from frame 30 on; MARK is logged at its frame.
    assert_eq!(run.param(29, 1, "gain"), 1.0);
    assert_eq!(run.param(30, 1, "gain"), 2.0);
    assert_eq!(run.events_of("mark")[0]["seq"], 33);
    let trig: Vec<(u64, &str)> =
        run.events_of("trigger").iter().map(|e| (e["seq"].as_u64().unwrap(), e["command"].as_str().unwrap())).collect();
    assert_eq!(trig, vec![(7, "START flash"), (30, "SET gain_offset#1.gain 2"), (33, "MARK done")]);

    // STOP ends it early; a second START restarts the two seconds.
    let run = drive(text, 60, 10.0, &[(5, "START flash"), (9, "STOP flash"), (12, "START glint")]);
    assert_eq!(run.enabled(0), [5, 6, 7, 8].into_iter().chain(12..32).collect::<Vec<u64>>());
    assert_eq!(run.events_of("event_stop")[0]["reason"], "command");

    // Disarmed: START is refused (NAK logged), ARM re-enables triggers.
    let armed_text = format!("{text}[triggers]\narmed = false\n");
    let run = drive(&armed_text, 20, 10.0, &[(2, "START flash"), (4, "ARM"), (6, "START flash")]);
    assert_eq!(run.enabled(0).first(), Some(&6));
    let nak = run.events_of("nak");
    assert_eq!(nak.len(), 1);
    assert!(nak[0]["reason"].as_str().unwrap().contains("disarmed"), "{:?}", nak[0]);
    // An event still active at the end of the stream is closed there.
    assert_eq!(run.events_of("event_stop").last().unwrap()["reason"], "end_of_stream");
}

#[test]
fn validation_names_every_problem_with_line_and_field() {
    let text = "seed = 1\n\
                [[effects]]\n\
                name = \"gain_offset\"\n\
                [[events]]\n\
                name = \"a\"\n\
                effect = \"gain_offset\"\n\
                at_frame = 3\n\
                duraton_frames = 2\n\
                [[events]]\n\
                name = \"b\"\n\
                effect = \"blooming\"\n\
                at_frame = 1\n\
                [[events]]\n\
                name = \"c\"\n\
                effect = \"gain_offset\"\n\
                duration_frames = 4\n\
                [events.params]\n\
                gain = { linear = [1.0, 9.0] }\n";
    let cfg = FaultConfig::parse(text, "bad.toml").unwrap();
    let err = Campaign::from_config(&cfg).unwrap_err().to_string();
    let lines: Vec<&str> = err.lines().collect();
    assert!(
        lines.iter().any(|l| l.starts_with("bad.toml:8: event 'a' field 'duraton_frames': unknown field")),
        "{err}"
    );
    assert!(
        lines.iter().any(|l| l.starts_with("bad.toml:11: event 'b' field 'effect'") && l.contains("blooming")),
        "{err}"
    );
    assert!(lines.iter().any(|l| l.starts_with("bad.toml:13: event 'c' field 'start': missing start")), "{err}");
    assert!(
        lines.iter().any(|l| l.starts_with("bad.toml:18: event 'c' field 'params.gain'") && l.contains("0..=4")),
        "{err}"
    );
}

#[test]
fn every_example_campaign_validates() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("hil/campaigns");
    let mut n = 0;
    for e in std::fs::read_dir(&dir).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "toml") {
            let cfg = FaultConfig::load(&p).unwrap_or_else(|e| panic!("{e}"));
            Campaign::from_config(&cfg).unwrap_or_else(|e| panic!("{e}"));
            Chain::from_config(&cfg).unwrap();
            n += 1;
        }
    }
    assert!(n >= 4, "the examples are there ({n})");
}

#[test]
fn the_readme_campaign_example_validates() {
    let readme = std::fs::read_to_string(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("README.md")).unwrap();
    let section = &readme[readme.find("## Campaigns and triggers").expect("the section")..];
    let start = section.find("```toml\n").expect("a TOML example") + "```toml\n".len();
    let text = &section[start..start + section[start..].find("```").unwrap()];
    let cfg = FaultConfig::parse(text, "README.md").unwrap_or_else(|e| panic!("{e}"));
    let c = Campaign::from_config(&cfg).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(c.events.len(), 2);
    // On trigger "flash": blooming for 2 s at 10 fps = 20 frames.
    let run = drive(text, 60, 10.0, &[(5, "START flash")]);
    assert_eq!(run.enabled(0), (5..25).collect::<Vec<u64>>());
}
