"""Secrets (issue 89): a storage URL's password is shown masked everywhere the package prints or
suggests it (an unreachable storage's error, the envelope command the report and the summary suggest),
however the URL gives it."""

import pytest

from explorer.study import storage


def test_an_unreachable_storage_is_named_without_its_password(run_cli, tmp_path):
    code, out, err = run_cli("search", "--study", "leak", "--reports", tmp_path, "--trials", "1",
                             "--storage", "postgresql://root:S3cretPw@127.0.0.1:5999/x")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "unreachable" in err
    assert "S3cretPw" not in err + out and "root:***@127.0.0.1:5999" in err
    assert storage.redacted("postgresql://u@h/x") == "postgresql://u@h/x"
    assert storage.redacted("journal:reports/x/journal.log") == "journal:reports/x/journal.log"


@pytest.mark.parametrize("url, shown", [
    ("postgresql://root:S3cretPw@127.0.0.1:5999/x", "postgresql://root:***@127.0.0.1:5999/x"),
    ("postgresql://root:S3cret/Pw@h/x", "postgresql://root:***@h/x"),           # a '/' in the password
    ("postgresql://root:S3cret@Pw@h/x", "postgresql://root:***@h/x"),           # an '@' in it
    ("postgresql://root@h/x?password=S3cretPw&sslmode=require", "postgresql://root@h/x?password=***&sslmode=require"),
    ("postgresql://h/x?user=root&PASSWORD=S3cretPw", "postgresql://h/x?user=root&PASSWORD=***"),
    ("mysql://root:S3cretPw@h:notaport/x", "mysql://root:***@h:notaport/x"),
    ("sqlite:///a:b@c.db", "sqlite:///a:b@c.db"),                               # a file name, no password
    ("postgresql://u:@h/x", "postgresql://u:@h/x"),
])
def test_a_storage_url_is_shown_with_every_password_masked(url, shown):
    assert storage.redacted(url) == shown and "S3cret" not in storage.redacted(url)


@pytest.mark.parametrize("url", ["postgresql://me@db.lab/studies?password=S3cretPw",
                                 "postgresql://me:S3cret/Pw@db.lab/studies", "mysql://me:S3cretPw@db.lab:noport/s"])
def test_the_envelope_command_masks_the_storage_password_however_the_url_gives_it(url):
    """The command the report and the search's summary suggest (explorer envelope --storage ...)."""
    from explorer.study.envelope import envelope_command
    from explorer.study.storage import redacted
    command = envelope_command("s", url)
    assert "S3cret" not in command and command.endswith(f"--storage {redacted(url)}")
