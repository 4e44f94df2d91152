import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.hal.pwm import MavlinkServoPwm, Pca9685Pwm, SysfsPwm, open_pwm, prescale_for


class RecordingBus:
    def __init__(self):
        self.writes = []

    def write(self, addr, data):
        self.writes.append((addr, bytes(data)))

    def read(self, addr, n):
        return bytes(n)

    def write_read(self, addr, data, n):
        raise AssertionError("not used")

    def close(self):
        pass


def test_that_the_pca9685_runs_at_50_hz_and_sets_the_pulse_in_ticks():
    assert prescale_for(50.0) == 121
    bus = RecordingBus()
    pwm = Pca9685Pwm(bus, 0x40, channel=3)
    assert (0x40, bytes([0xFE, 121])) in bus.writes
    pwm.set_pulse_us(1500)
    _addr, data = bus.writes[-1]
    ticks = data[3] | data[4] << 8
    assert data[0] == 0x06 + 4 * 3
    assert ticks * 1e6 / (4096 * pwm.actual_frame_hz) == pytest.approx(1500, abs=5)
    with pytest.raises(ValueError):
        pwm.set_pulse_us(float("nan"))


def test_that_sysfs_pwm_writes_period_and_duty(tmp_path):
    chip = tmp_path / "pwmchip0"
    (chip / "pwm1").mkdir(parents=True)
    (chip / "export").write_text("")
    pwm = SysfsPwm(0, 1, root=tmp_path)
    pwm.set_pulse_us(1250)
    assert (chip / "pwm1" / "period").read_text() == "20000000"
    assert (chip / "pwm1" / "duty_cycle").read_text() == "1250000"
    with pytest.raises(OSError, match="no PWM chip"):
        SysfsPwm(7, 0, root=tmp_path)


def test_that_the_autopilot_servo_is_commanded_with_do_set_servo():
    sent = []

    class Link:
        def send(self, msg):
            sent.append(msg)

    pwm = MavlinkServoPwm(Link(), 9, mavlink.MAVLink(None, 1, 191))
    pwm.set_pulse_us(1700)
    assert sent[-1].command == 183 and sent[-1].param1 == 9 and sent[-1].param2 == 1700


@pytest.mark.parametrize("url", ["pwm", "pwm:sysfs:0", "pwm:pca9685:1:zz:0", "pwm:warp:1", "pwm:mavlink:9"])
def test_that_bad_pwm_urls_are_refused_with_a_message(url):
    with pytest.raises(ValueError, match="PWM"):
        open_pwm(url)


@pytest.mark.parametrize("url", ["pwm:pca9685:1:0x80:0", "pwm:pca9685:1:zz:0", "pwm:pca9685:1:0x40:x"])
def test_that_a_bad_pca9685_address_or_channel_is_refused_before_the_bus_is_opened(url):
    opened = []
    with pytest.raises(ValueError, match="bad PWM output"):
        open_pwm(url, i2c_opener=opened.append)
    assert opened == []


def test_that_the_pca9685_bus_is_closed_when_the_output_cannot_be_set_up():
    class Bus(RecordingBus):
        closed = False

        def close(self):
            self.closed = True

    bus = Bus()
    with pytest.raises(ValueError, match="channel must be 0-15"):
        open_pwm("pwm:pca9685:1:0x40:16", i2c_opener=lambda _url: bus)
    assert bus.closed
