"""Tables in docs/ that state what the code does: they must say what it does."""
from pathlib import Path

from ibvs_control.mavlink.safety import POLICY

DOCS = Path(__file__).resolve().parents[2] / 'docs'


def test_the_documented_table_is_the_policy():
    text = (DOCS / 'mavlink.md').read_text()
    table = text[text.index('## Safety policy'):]
    rows = [line for line in table.splitlines() if line.startswith('|')][2:]   # header, ---
    documented = [tuple(c.strip() for c in row.strip('|').split('|')) for row in rows
                  if row.count('|') == 4][:len(POLICY)]
    assert documented == [(r.event, r.action, r.who) for r in POLICY]
