// faultcam trigger rig: an Arduino (Uno, Nano, Leonardo, any board with a USB serial port)
// that sends trigger commands to `faultcam run --trigger /dev/ttyACM0` and checks the replies.
// Protocol: hil/trigger-protocol.md.
//
//   * Push button on pin 2 (to GND, internal pull-up): START flash on press.
//   * Photodiode / light sensor on A0: START flash when the level rises above THRESHOLD
//     (e.g. the sun glint of a rotating mock-up crossing the camera's view), with hysteresis.
//   * Button on pin 3: STOP flash.
//   * Every command carries a new sequence number; the reply is matched by it:
//     LED on pin 13 blinks once per ACK, fast three times per NAK. Unanswered commands are
//     retransmitted with the same sequence number (faultcam re-acknowledges without applying
//     them twice).
//   * At boot the rig sends PING until faultcam answers: the stream is running.
//   * The replies carry the frame at which each change took effect; on boards with a second
//     UART the sketch copies them to Serial1 for a data logger.
//
// Build: Arduino IDE or `arduino-cli compile --fqbn arduino:avr:uno hil/trigger-firmware`.

const long BAUD = 115200;              // faultcam's default (--trigger /dev/ttyACM0?baud=115200)
const int PIN_START = 2;
const int PIN_STOP = 3;
const int PIN_LIGHT = A0;
const int PIN_LED = 13;
const int THRESHOLD = 600;             // ADC counts (0..1023): glint present
const int HYSTERESIS = 50;
const unsigned long DEBOUNCE_MS = 30;
const unsigned long RETRY_MS = 250;    // resend an unanswered command after this long
const int MAX_RETRIES = 4;

unsigned long seq = 1;                 // next sequence number
unsigned long pendingSeq = 0;          // awaiting a reply (0 = none)
char pendingCmd[48];
unsigned long pendingSince = 0;
int retries = 0;
bool linkUp = false;

char line[96];
int lineLen = 0;

bool lastStart = HIGH, lastStop = HIGH;
unsigned long startChanged = 0, stopChanged = 0;
bool glint = false;

void blink(int times, int ms) {
  for (int i = 0; i < times; i++) {
    digitalWrite(PIN_LED, HIGH);
    delay(ms);
    digitalWrite(PIN_LED, LOW);
    delay(ms);
  }
}

// Send "<seq> <cmd>\n" and remember it until the reply comes.
void send(const char *cmd) {
  if (pendingSeq != 0) return;         // one command in flight at a time
  pendingSeq = seq++;
  strncpy(pendingCmd, cmd, sizeof(pendingCmd) - 1);
  pendingCmd[sizeof(pendingCmd) - 1] = 0;
  retries = 0;
  pendingSince = millis();
  Serial.print(pendingSeq);
  Serial.print(' ');
  Serial.print(pendingCmd);
  Serial.print('\n');
}

void resend() {
  pendingSince = millis();
  retries++;
  Serial.print(pendingSeq);
  Serial.print(' ');
  Serial.print(pendingCmd);
  Serial.print('\n');
}

// "ACK 12 frame=345 t_ns=11500000000" or "NAK 12 reason" or "NAK - reason" or "EDGE ...".
void handleReply(const char *l) {
  bool ack = strncmp(l, "ACK ", 4) == 0;
  bool nak = strncmp(l, "NAK ", 4) == 0;
  if (!ack && !nak) return;
  unsigned long s = strtoul(l + 4, NULL, 10);
  if (pendingSeq != 0 && s == pendingSeq) {
    pendingSeq = 0;
    if (ack) {
      linkUp = true;
      blink(1, 40);
    } else {
      blink(3, 30);
    }
  } else if (nak) {
    blink(3, 30);                      // garbage we sent, or a NAK for an older command
  }
#if defined(HAVE_HWSERIAL1)
  Serial1.println(l);                  // frame-stamped log for a data logger
#endif
}

void readReplies() {
  while (Serial.available() > 0) {
    char c = Serial.read();
    if (c == '\n' || c == '\r') {
      if (lineLen > 0) {
        line[lineLen] = 0;
        handleReply(line);
        lineLen = 0;
      }
    } else if (lineLen < (int)sizeof(line) - 1) {
      line[lineLen++] = c;
    }
  }
}

// A debounced falling edge (button pressed) on `pin`.
bool pressed(int pin, bool &last, unsigned long &changed) {
  bool v = digitalRead(pin);
  if (v != last && millis() - changed > DEBOUNCE_MS) {
    changed = millis();
    last = v;
    return v == LOW;
  }
  return false;
}

void setup() {
  pinMode(PIN_START, INPUT_PULLUP);
  pinMode(PIN_STOP, INPUT_PULLUP);
  pinMode(PIN_LED, OUTPUT);
  Serial.begin(BAUD);
#if defined(HAVE_HWSERIAL1)
  Serial1.begin(BAUD);
#endif
  while (!Serial) {
  }                                    // boards with native USB: wait for the host
}

void loop() {
  readReplies();
  if (pendingSeq != 0 && millis() - pendingSince > RETRY_MS) {
    if (!linkUp || retries < MAX_RETRIES) {
      resend();                        // PING is repeated until faultcam runs
    } else {
      pendingSeq = 0;                  // give up on this command
      blink(5, 20);
    }
  }
  if (!linkUp) {
    send("PING");
    return;
  }
  if (pressed(PIN_START, lastStart, startChanged)) send("START flash");
  if (pressed(PIN_STOP, lastStop, stopChanged)) send("STOP flash");
  int level = analogRead(PIN_LIGHT);
  if (!glint && level > THRESHOLD + HYSTERESIS) {
    glint = true;
    send("START flash");
  } else if (glint && level < THRESHOLD - HYSTERESIS) {
    glint = false;
    send("MARK glint gone");
  }
}
