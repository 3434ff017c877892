#!/bin/bash
# usage: fresh.sh label commit warm|cold
label=$1; commit=$2; mode=$3
dir=/tmp/fc_$label; rm -rf $dir
out=/work/notes/fc_$label.txt
if [ "$mode" = cold ]; then
  rm -rf /root/.cache/uv /root/.cache/pip /root/.cache/ggns
  apt-get remove -y -qq libusb-1.0-0 >/dev/null 2>&1
  echo "caches: ~/.cache/uv, ~/.cache/pip, ~/.cache/ggns removed, apt package libusb-1.0-0 removed" > $out
else
  echo "caches: present (uv, pip, torch-cluster wheel; libusb-1.0-0 installed)" > $out
fi
echo "start $(date -u +%FT%TZ) commit $commit" >> $out
s=$(date +%s.%N)
git clone -q /work/main $dir && cd $dir && git checkout -q $commit && (.ci/run >> $out 2>&1; echo "rc=$?" >> $out)
e=$(date +%s.%N)
echo "total=$(echo "$e - $s" | bc) s (git clone, checkout and .ci/run)" >> $out
