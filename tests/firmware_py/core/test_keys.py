"""Key files are parsed strictly: a decorated hex key is refused in one line naming the decoration (it
would otherwise hash silently into another key), and a key others could read or replace is refused."""

from __future__ import annotations

import os

import pytest

from firmware_py.core.keys import key_from_passphrase, load_key, parse_key_text

KEY = bytes(range(1, 33))
HEX = KEY.hex()
posix_only = pytest.mark.skipif(os.name != "posix", reason="POSIX permission bits")


def key_file(folder, content, mode: int = 0o600, name: str = "link.key"):
    path = folder / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    path.chmod(mode)
    return path


@pytest.mark.parametrize(("content", "named"), [
    ("\ufeff" + HEX, "byte-order mark"),
    ("\ufeffcorrect horse battery staple", "byte-order mark"),
    ("0x" + HEX, "0x prefix"),
    ("0X" + HEX.upper(), "0x prefix"),
    (HEX + "  # ground station key", "trailing comment"),
    (HEX + "#", "trailing comment"),
    (" ".join(HEX[i:i + 8] for i in range(0, 64, 8)), "whitespace between the digits"),
    (HEX[:32] + "\t" + HEX[32:], "whitespace between the digits"),
    ("0x" + HEX[:-1], "63 hex digits"),
    ("0x" + HEX + " # old key", "0x prefix"),
])
def test_that_a_decorated_hex_key_is_refused_in_one_line_naming_the_decoration(tmp_path, content, named):
    path = key_file(tmp_path, content)
    with pytest.raises(ValueError) as err:
        load_key(path)
    msg = str(err.value)
    assert named in msg and str(path) in msg and "\n" not in msg


@pytest.mark.parametrize("content", [HEX, HEX + "\n", "  " + HEX + "\r\n", HEX.upper() + "\n"])
def test_that_a_bare_hex_key_with_surrounding_whitespace_and_one_line_ending_is_the_key(content):
    assert parse_key_text(content) == KEY


@pytest.mark.parametrize("phrase", ["correct horse battery staple", "secret#2024-pile", "0xygen-tank-42",
                                    "my key # not a hex line"])
def test_that_passphrases_with_a_non_hex_word_stay_passphrases(phrase):
    assert parse_key_text(phrase + "\n") == key_from_passphrase(phrase)


@posix_only
@pytest.mark.parametrize("mode", [0o620, 0o660, 0o622])
def test_that_a_group_writable_key_file_is_refused(tmp_path, mode):
    path = key_file(tmp_path, HEX, mode=mode)
    with pytest.raises(ValueError, match=r"(writable by its group|accessible by everyone).*chmod 600"):
        load_key(path)


@posix_only
@pytest.mark.parametrize(("mode", "who"), [(0o777, "everyone"), (0o770, "its group"), (0o1777, "everyone"),
                                           (0o702, "everyone")])
def test_that_a_key_in_a_folder_others_can_write_is_refused(tmp_path, mode, who):
    folder = tmp_path / "keys"
    folder.mkdir()
    path = key_file(folder, HEX)
    folder.chmod(mode)
    with pytest.raises(ValueError) as err:
        load_key(path)
    msg = str(err.value)
    assert f"folder writable by {who}" in msg and str(folder) in msg and "chmod go-w" in msg and "\n" not in msg


@posix_only
def test_that_a_writable_folder_higher_up_is_refused_unless_it_is_sticky(tmp_path):
    top = tmp_path / "shared"
    (top / "mine").mkdir(parents=True)
    path = key_file(top / "mine", HEX)
    (top / "mine").chmod(0o700)
    top.chmod(0o777)
    with pytest.raises(ValueError, match="folder writable by everyone"):
        load_key(path)
    top.chmod(0o1777)  # like /tmp: others cannot rename our folder away
    assert load_key(path) == KEY


@posix_only
@pytest.mark.parametrize("mode", [0o700, 0o750, 0o755])
def test_that_a_key_in_a_private_or_read_only_shared_folder_is_accepted(tmp_path, mode):
    folder = tmp_path / "keys"
    folder.mkdir()
    path = key_file(folder, HEX)
    folder.chmod(mode)
    assert load_key(path) == KEY
