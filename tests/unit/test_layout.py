"""The package layout (docs/architecture.md): dependencies point one way, every package used is
declared in package.xml, and the table of ports in the documentation is the code's."""
import ast
import glob
import os
import re
import xml.etree.ElementTree as ET

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SRC = os.path.join(ROOT, 'catkin_ws', 'src')
OURS = ('aft_msgs', 'aft_ftm', 'aft_service_manager', 'aft_examples', 'tjp_sim', 'aft_bench')
# What each package may use, besides itself (the picture in docs/architecture.md).
ALLOWED = {
    'aft_msgs': set(),
    'aft_ftm': {'aft_msgs'},
    'aft_service_manager': {'aft_msgs', 'aft_ftm'},
    'aft_examples': {'aft_msgs', 'aft_ftm'},
    'tjp_sim': {'aft_msgs', 'aft_ftm', 'aft_service_manager'},
    'aft_bench': {'aft_msgs', 'aft_ftm', 'aft_examples', 'aft_service_manager', 'tjp_sim'},
}


def files_of(package, test_code=False):
    base = os.path.join(SRC, package)
    paths = glob.glob(os.path.join(base, 'src', '**', '*.py'), recursive=True)
    paths += glob.glob(os.path.join(base, 'nodes', '*'))
    paths += glob.glob(os.path.join(base, 'launch', '*.launch')) + glob.glob(os.path.join(base, 'adaptations', '*'))
    paths += glob.glob(os.path.join(base, 'config', '*'))
    if test_code:
        paths += glob.glob(os.path.join(base, 'test', '*'))
    return [p for p in paths if os.path.isfile(p) and not p.endswith('.pyc')]   # not __pycache__


def packages_used(path):
    """Our packages a file uses: Python imports, launch pkg= and $(find ...), rosrun and
    package/file references in scripts and configurations."""
    text = open(path, errors='replace').read()
    used = set()
    if path.endswith('.py') or text.startswith('#!/usr/bin/env python'):
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.Import):
                used |= {a.name.split('.')[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                used.add(node.module.split('.')[0])
        # module paths named in strings (assertions package.module:function, launch specs)
        used |= set(re.findall(r"['\"](%s)[./:]" % '|'.join(OURS), text))
    else:
        used |= set(re.findall(r'pkg="(\w+)"', text)) | set(re.findall(r'\$\(find (\w+)\)', text))
        used |= set(re.findall(r'rosrun (\w+)', text)) | set(re.findall(r'\b(%s)[./:]' % '|'.join(OURS), text))
    return used & set(OURS)


@pytest.mark.parametrize('package', sorted(ALLOWED))
def test_dependencies_point_one_way(package):
    wrong = {}
    for path in files_of(package, test_code=package != 'aft_bench'):
        above = packages_used(path) - ALLOWED[package] - {package}
        if above:
            wrong[os.path.relpath(path, SRC)] = sorted(above)
    assert not wrong, '%s uses packages above it: %s' % (package, wrong)


@pytest.mark.parametrize('package', sorted(ALLOWED))
def test_every_package_used_is_declared(package):
    xml = ET.parse(os.path.join(SRC, package, 'package.xml')).getroot()
    declared = {e.text.strip() for e in xml if e.tag.endswith('depend')}
    used = set()
    for path in files_of(package):
        used |= packages_used(path)
    missing = used - declared - {package}
    assert not missing, '%s/package.xml does not declare %s' % (package, sorted(missing))


def ports_in_code():
    """{class name: [(direction, port)]} of every class declaring PortSpecs in aft_ftm's adapters."""
    found = {}
    for path in glob.glob(os.path.join(SRC, 'aft_ftm', 'src', 'aft_ftm', 'ros', '*.py')):
        text = open(path).read()
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ClassDef):
                ports = re.findall(r"PortSpec\('(\w+)',\s*(PUBLISH|SUBSCRIBE)", ast.get_source_segment(text, node))
                if ports:
                    found[node.name] = [('>' if d == 'PUBLISH' else '<', name) for name, d in ports]
    return found


def test_the_documented_ports_are_the_code_s():
    doc = open(os.path.join(ROOT, 'docs', 'architecture.md')).read()
    rows = {m.group(1): m.group(2) for m in re.finditer(r'^\|[^|]*\(`(\w+)`\) \| (.*) \|$', doc, re.M)}
    code = ports_in_code()
    assert len(code) >= 12
    problems = []
    for cls, ports in sorted(code.items()):
        if cls not in rows:
            problems.append('%s has no row' % cls)
            continue
        problems += ['%s: port %s%s not documented' % (cls, d, p) for d, p in ports if '`%s%s`' % (d, p) not in rows[cls]]
    assert not problems, 'docs/architecture.md ports table: %s' % '; '.join(problems)
